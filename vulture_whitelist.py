"""Names that vulture (the dead-code check in tests/test_style.py) cannot see being used.

Only genuine false positives belong here, each with who uses it; dead code is removed instead.
vulture reads this file as source, never runs it.
"""
# ruff: noqa: B018  (attribute reads are how a vulture whitelist marks names used)

from vulture.whitelist_utils import Whitelist

_ = Whitelist()

# called by frameworks
_.forward  # torch.nn.Module.__call__ (spk2img/model, spk2img/export/onnx_export.py)
_.get_next  # onnxruntime's CalibrationDataReader (spk2img/export/quantize.py)
_.healthz  # FastAPI routes, registered by their decorators (spk2img/service/routers)
_.readyz
_.list_models
_._one_selector  # a pydantic model_validator (spk2img/service/schemas.py)
_.background  # read by FastAPI/Starlette on a Response (spk2img/service/duplex.py)

# fields of the service's answers, serialised by pydantic (spk2img/service/schemas.py)
_.file
_.methods

# attributes set for a library to read
_.enable_cpu_mem_arena  # onnxruntime.SessionOptions
_.intra_op_num_threads
_.inter_op_num_threads
_.writeable  # numpy's ndarray.flags
_.enable_profiling  # onnxruntime.SessionOptions (spk2img/bench/profile.py)
_.profile_file_prefix

# public API that only the tests use inside this repository
_.write_spikes  # spk2img.io.spikes: writes a stream as .dat, .npy or .npz
_.codes_held  # spk2img.runtime.block_stream.BlockReuseStream: what a stream holds

# called from a shell script
_.release_checkpoint  # spk2img/model/checkpoint.py: called by scripts/ship_model.sh

# module hooks Python itself calls (PEP 562): spk2img/__init__.py loads its public API lazily
_.__getattr__
_.__dir__

# asyncio and uvicorn call these (spk2img/service/server.py's protocol)
_.eof_received  # asyncio.Protocol: the client shut down its write side (half-close)
_.keep_alive  # uvicorn's RequestResponseCycle: close the connection after the response

# used by scripts/real_capture_quality.py (scripts are not scanned) and the tests
_.niqe  # spk2img.evaluation.niqe
_.display_grey  # spk2img.evaluation.niqe

# used by scripts/average_checkpoints.py (scripts are not scanned) and the tests
_.average_checkpoints  # spk2img/model/checkpoint.py
_.SELECTIONS  # spk2img/training/train.py: the choices of its --chosen-on

# FastAPI routes of the viewer (spk2img/service/routers/viewer.py), registered by their decorators
_.page
_.static_file
_.api_page

# functools.singledispatch registrations of spk2img/sim/torch_render.py's render, per scene type
_._moving
_._layered
_._clip
_._still

# uvicorn.Server: the hook _ProbeServer overrides, and the flags that stop a server
# (spk2img/service/server.py's Listeners)
_.capture_signals
_.should_exit
_.force_exit

# pydantic field validator of ServiceSettings, called by pydantic
_._device_runs_here  # spk2img.service.settings

# used by scripts/spike_reds_benchmark.py (scripts are not scanned) and the tests
_.toolkit_data_root  # spk2img/evaluation/spike_reds.py
_.find_streams
_.load_window
# spk2img/evaluation/scoring.py, used by scripts/real_video_validation.py and
# scripts/spike_reds_benchmark.py
_.network_methods
_.dates_made  # the "Made by" dates of both scripts' results files
_.commands_made  # the "Made by" commands of both scripts' results files
