#!/usr/bin/env bash
# The commands of a lent GPU session (docs/gpu.md, "A GPU session"), each under 10 minutes,
# each writing what it measured under $OUT (the folder that comes back: 8 files at most).
# Here, before the session:
#   scripts/gpu_session.sh prepare DATA         # the training data as one part that fits beside
#                                               # this checkout in one command (pack/, git-ignored)
#   scripts/gpu_session.sh prepare-onnx [ARCH]  # onnxruntime-gpu for sm_ARCH (90: H100, H200) in
#                                               # parts of that size (pack-onnx/, git-ignored)
# There, run from the checkout, with `pack` carried:
#   scripts/gpu_session.sh session SECONDS      # env, torch inference rows, synthesis speed,
#                                               # then the runs of scripts/gpu_runs.txt trained
#                                               # side by side for SECONDS, stopped, brought back
#   scripts/gpu_session.sh more SECONDS         # the next command, while the machine is warm:
#                                               # the same runs resumed for SECONDS
#   scripts/gpu_session.sh receive MANIFEST DEST # one part of a split file (receive_parts.sh)
#   scripts/gpu_session.sh onnx                  # onnxruntime-gpu rows (after receiving it): the
#                                               # bench's GPU rows, fp16 parity, TensorRT's probe
#   scripts/gpu_session.sh train-start NAME SECONDS ARGS…
#                                 # one run in the background (its own process session, so it
#                                 # outlives the command) in /tmp/spk2img-runs/NAME
#   scripts/gpu_session.sh train-stop NAME
#                                 # Ctrl-C to it (it saves last.pt at its step), then its log and
#                                 # metrics into $OUT/report/NAME and its checkpoints into $OUT
# What `session` and `more` bring back: $OUT/report.tar.gz (environment.txt, the measurements'
# JSON and logs, each run's train.log and metrics.jsonl) and $OUT/NAME-last.pt, NAME-best.pt
# (a checkpoint over 15 MiB comes back as its weights alone in fp16).
set -euo pipefail
out=${OUT:-/tmp/spk2img-out}
mkdir -p "$out"
export PYTHONPATH="$PWD${PYTHONPATH:+:$PYTHONPATH}"
ort=/tmp/spk2img-ort-gpu   # where receive installs the onnxruntime-gpu wheel
runs=${SPK2IMG_RUNS:-/tmp/spk2img-runs}   # where the runs train
data=${SPK2IMG_DATA:-/tmp/spk2img-data}   # where session unpacks the training data
run_list=${SPK2IMG_SESSION_RUNS:-scripts/gpu_runs.txt}
pack=${SPK2IMG_PACK:-pack}   # the folder prepare writes and the session's command carries
ort_version=1.31.1   # the newest onnxruntime-gpu (docs/gpu.md), for the GPU machine's Python 3.12
step=${1:?prepare, prepare-onnx, session, more, receive, onnx, train-start or train-stop}
shift

start_run() {  # NAME SECONDS ARGS…: train in the background, SIGINT after SECONDS
  local name=$1 seconds=$2
  shift 2
  mkdir -p "$runs/$name"
  setsid nohup timeout --signal=INT "$seconds" python3 -m spk2img train --device cuda \
    --synthesis torch --no-progress --run-dir "$runs/$name" "$@" \
    >> "$runs/$name/train.log" 2>&1 < /dev/null &
  echo "training $name in the background for at most $seconds s: $runs/$name"
}

running() {  # NAME: is its training process alive?
  pgrep -f "spk2img train .*--run-dir $runs/$1( |\$)" > /dev/null
}

stop_run() {  # NAME: Ctrl-C to the training process alone (timeout would pass it on twice)
  pkill -INT -f "^python3 -m spk2img train .*--run-dir $runs/$1( |\$)" || echo "$1: not running"
  for _ in $(seq 240); do
    running "$1" || break
    sleep 0.5
  done
}

bring_back() {  # NAME: log and metrics into $out/report/NAME, checkpoints into $out
  local name=$1 f
  mkdir -p "$out/report/$name"
  for f in train.log metrics.jsonl; do
    if [ -f "$runs/$name/$f" ]; then cp "$runs/$name/$f" "$out/report/$name/"; fi
  done
  for f in last best; do
    [ -f "$runs/$name/$f.pt" ] || continue
    if [ "$(stat -c %s "$runs/$name/$f.pt")" -gt $((15 * 1024 * 1024)) ]; then
      python3 -c "import sys, torch; from spk2img.model.checkpoint import release_checkpoint as r
r(sys.argv[1], sys.argv[2], torch.float16)" "$runs/$name/$f.pt" "$out/$name-$f.pt"
    else
      cp "$runs/$name/$f.pt" "$out/$name-$f.pt"
    fi
  done
  tail -n 3 "$runs/$name/train.log"
}

read_pack() {  # data_flags: --data for each folder of the unpacked pack, as PACK.json names them
  local folder
  data_flags=()
  for folder in $(python3 -c "import json, sys; print(*json.load(open(sys.argv[1]))['folders'])" \
      "$data/PACK.json"); do
    data_flags+=(--data "$data/$folder")
  done
}

train_listed() {  # SECONDS: every run of $run_list side by side, then stopped and brought back
  local seconds=$1 name args names=() sources=()
  read_pack
  sources=("${data_flags[@]}")
  # the real-video validation's windows that pack-data filmed from the clips it left here
  if [ -f "$data/real_video_windows.npz" ]; then
    sources+=(--real-video-windows "$data/real_video_windows.npz")
  fi
  while read -r name args; do
    case "$name" in ''|'#'*) continue ;; esac
    # shellcheck disable=SC2086  # the flags are words
    start_run "$name" "$seconds" $args "${sources[@]}"
    names+=("$name")
  done < "$run_list"
  sleep 2
  for _ in $(seq $((seconds + 60))); do  # timeout stops each at SECONDS; each saves its step
    alive=0
    for name in "${names[@]}"; do if running "$name"; then alive=1; fi; done
    [ "$alive" = 1 ] || break
    sleep 1
  done
  for name in "${names[@]}"; do
    if running "$name"; then stop_run "$name"; fi
    bring_back "$name"
  done
  tar -czf "$out/report.tar.gz" -C "$out" report && rm -rf "$out/report"
}

case "$step" in
  prepare)
    # here: what a command carries beside this checkout, then the training data cut to fit it
    room=$(python -m spk2img.parts room .)
    rm -rf "$pack"
    spk2img pack-data --data "${1:?the training data folder}" --out "$pack" \
      --max-mib "$room" --part-mib "$room"
    echo "carry: $pack ($room MiB beside the checkout)"
    ;;
  prepare-onnx)
    # here: onnxruntime-gpu with the CUDA kernels of one architecture, in parts of the room, and
    # the serve extra's wheels that the GPU machine's image lacks (for the service's GPU rows)
    arch=${1:-90}
    room=$(python -m spk2img.parts room .)
    wheel=wheels/onnxruntime_gpu-$ort_version-cp312-cp312-manylinux_2_28_x86_64.whl
    slim=wheels/onnxruntime-gpu-$ort_version-sm_$arch.tar.xz
    for312=(--only-binary=:all: --python-version 3.12 --implementation cp
      --platform manylinux_2_28_x86_64 --platform manylinux_2_17_x86_64
      --platform manylinux2014_x86_64)
    [ -f "$wheel" ] || pip download "onnxruntime-gpu==$ort_version" --no-deps -d wheels "${for312[@]}"
    python scripts/slim_onnxruntime_gpu.py "$wheel" --arch "$arch" --out "$slim"
    rm -rf pack-onnx
    python -m spk2img.parts split "$slim" --out pack-onnx --part-mib "$room"
    # shellcheck disable=SC2046  # the serve extra's pins, one word each
    pip download -q -d pack-onnx/serve-wheels "${for312[@]}" $(python -c "import tomllib
extra = tomllib.load(open('pyproject.toml', 'rb'))['project']['optional-dependencies']['serve']
print(*(pin for pin in extra if not pin.startswith('onnxruntime')))")
    manifest=pack-onnx/$(basename "$slim").parts.json
    parts=(pack-onnx/*.part-*)
    receive="scripts/gpu_session.sh receive $manifest $ort"
    for part in "${parts[@]}"; do
      carry="\"$manifest\", \"$part\""
      if [ "$part" = "${parts[-1]}" ]; then
        carry="$carry, \"pack-onnx/serve-wheels\""
        receive="$receive && scripts/gpu_session.sh onnx"
      fi
      echo "carry [$carry]: $receive"
    done
    last=$(( $(stat -c %s "${parts[-1]}") + $(du -sb pack-onnx/serve-wheels | cut -f1) ))
    python -c "import sys; assert int(sys.argv[1]) <= float(sys.argv[2]) * 2**20, \
      'the last part and the serve wheels exceed the room: carry the wheels in a command of their own'" \
      "$last" "$room"
    ;;
  session)
    seconds=${1:?seconds of training}
    { python3 --version; nvidia-smi --query-gpu=name,driver_version,memory.total --format=csv
      python3 -c "import torch; print('torch', torch.__version__, 'cuda', torch.version.cuda)"
      nproc
    } > "$out/environment.txt" 2>&1 || true
    mkdir -p "$out/report" && mv "$out/environment.txt" "$out/report/"
    cat "$out/report/environment.txt"
    scripts/receive_parts.sh "$pack/training-data.zip.parts.json" "$data"
    read_pack
    if [ "${SPK2IMG_SESSION_MEASURE:-1}" = 1 ]; then
      timeout 100 python3 scripts/torch_inference_speed.py --device cuda --models default,cpu,tiny \
        --json "$out/report/torch_inference.json" > "$out/report/torch_inference.log" 2>&1 \
        || echo "torch inference rows: exit $?"
      timeout 90 python3 scripts/synthesis_speed.py --device cuda --workers 8 --batch-size 64 \
        --patch 64 --steps 8 --synthesis-batches 1 --precisions bf16 "${data_flags[@]}" \
        --json "$out/report/synthesis_speed_gpu.json" > "$out/report/synthesis_speed.log" 2>&1 \
        || echo "synthesis speed: exit $?"
    fi
    train_listed "$seconds"
    ;;
  more)
    mkdir -p "$out/report"
    train_listed "${1:?seconds of training}"
    ;;
  receive)
    scripts/receive_parts.sh "$@"
    ;;
  onnx)
    if [ -d pack-onnx/serve-wheels ]; then  # carried: what the service needs beside onnxruntime
      python3 -m pip install -q --no-index --no-deps --no-compile --target "$ort" \
        pack-onnx/serve-wheels/*.whl
    fi
    export PYTHONPATH="$ort:$PYTHONPATH"
    # the CUDA libraries of torch's nvidia wheels, for every process onnxruntime-gpu runs in
    nvidia=$(python3 -c "import nvidia; print(list(nvidia.__path__)[0])")
    libs=$(find "$nvidia" -name 'lib*.so*' -printf '%h\n' | sort -u | paste -sd:)
    export LD_LIBRARY_PATH="$libs${LD_LIBRARY_PATH:+:$LD_LIBRARY_PATH}"
    python3 -c "import onnxruntime as o; o.preload_dlls(); print(o.__version__, o.get_available_providers())" \
      | tee "$out/onnxruntime.txt"
    # the GPU rows go into a copy of this checkout's bench (rewritten after each row, so the
    # time limit keeps what was measured); the fp16 parity on the hard cases; TensorRT's probe
    mkdir -p "$out/bench" && cp docs/bench.json docs/bench.md "$out/bench/"
    timeout "${SPK2IMG_BENCH_S:-240}" python3 -m spk2img bench --gpu-only --device cuda \
      --repeats 3 --out-dir "$out/bench" > "$out/bench/bench.log" 2>&1 || echo "bench: exit $?"
    tail -n 5 "$out/bench/bench.log"
    timeout 90 python3 -m spk2img verify spk2img/assets/models/spk2img-default.onnx \
      --device cuda --fp16 --quick > "$out/verify_fp16_cuda.txt" 2>&1 || echo "verify: exit $?"
    timeout 45 python3 -m spk2img reconstruct examples/fast_motion_250x400.dat \
      --out /tmp/spk2img-trt.npz --device tensorrt > "$out/tensorrt.txt" 2>&1 \
      || echo "tensorrt: exit $?"
    ;;
  train-start)
    start_run "$@"
    ;;
  train-stop)
    name=${1:?name}
    stop_run "$name"
    bring_back "$name"
    ;;
  *)
    echo "unknown step $step: prepare, prepare-onnx, session, more, receive, onnx, train-start" \
      "or train-stop" >&2
    exit 2
    ;;
esac
