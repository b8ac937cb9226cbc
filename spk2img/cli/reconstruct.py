"""``spk2img reconstruct``: a spike file -> ``OUT.npz`` of frames (locally or through a service)."""

from __future__ import annotations

import argparse
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from spk2img import api
from spk2img.cli.arguments import check_output_folder, thread_count
from spk2img.cli.interrupts import exit_code, interrupt_message
from spk2img.cli.progress import add_progress_flags, progress_bar, say, show_progress
from spk2img.errors import InputError
from spk2img.io.frame_size import check_frame_size
from spk2img.io.frame_store import FrameStore
from spk2img.io.spikes import DEFAULT_HEIGHT, DEFAULT_WIDTH, DatStream
from spk2img.runtime.adaptive import QUALITIES, BalancedStream
from spk2img.runtime.binning import binning_for_rates, firing_rates
from spk2img.runtime.block_stream import BlockReuseStream
from spk2img.runtime.methods import DEFAULT_TFP_WINDOW, METHODS
from spk2img.runtime.onnx_backend import DEVICES
from spk2img.runtime.stream import NetStream
from spk2img.runtime.windows import MAX_BINNING, check_binning


def add_parser(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "reconstruct",
        help="reconstruct images from a spike stream",
        description="Reconstruct linear-intensity frames from a .dat/.npy/.npz spike stream and "
        "write OUT.npz with 'frames' (N, H, W) float32 and 'centers' (N,) int64.",
    )
    p.add_argument("input", type=Path, help=".dat (needs --height/--width) or .npy/.npz (T, H, W)")
    p.add_argument("--out", type=Path, required=True, help="output .npz")
    p.add_argument("--height", type=int, default=DEFAULT_HEIGHT, help="frame height of a .dat")
    p.add_argument("--width", type=int, default=DEFAULT_WIDTH, help="frame width of a .dat")
    p.add_argument(
        "--force-size",
        action="store_true",
        help="read a .dat at --height x --width even when its spikes look like noise at that "
        "size (by default such a size is refused with the likely sizes; spk2img inspect lists "
        "them)",
    )
    which = p.add_mutually_exclusive_group()
    which.add_argument("--centers", help="comma-separated centre frames, e.g. 40,80,120")
    which.add_argument(
        "--stride",
        type=int,
        help="every S-th centre with a full window (default: the model's block stride, 7 for "
        "the shipped models, so that each block is encoded once)",
    )
    p.add_argument("--method", choices=METHODS, default="net", help="default: net")
    p.add_argument("--window", type=int, default=DEFAULT_TFP_WINDOW, help="TFP's window (odd)")
    p.add_argument(
        "--quality",
        choices=QUALITIES,
        default="best",
        help="for --method net: best (the network everywhere, default), balanced (the network "
        "only on tiles that move or are dim, TFP elsewhere) or fast (TFP over the network's "
        "window)",
    )
    p.add_argument(
        "--binning",
        type=parse_binning,
        default=1,
        metavar="K|auto",
        help="for dim streams (--method net, --quality best): merge K consecutive frames into "
        "each of the network's frames, so a window spans K times its window; auto picks K from the "
        "stream's firing rate (default 1: none; docs/binning.md)",
    )
    p.add_argument(
        "--model",
        help="ONNX model file, or a shipped model's name (spk2img models lists them; default: "
        "the shipped default)",
    )
    p.add_argument("--backend", choices=("onnx", "torch"), default="onnx")
    p.add_argument("--checkpoint", type=Path, help="torch checkpoint for --backend torch")
    p.add_argument("--threads", type=thread_count, default=None, help="inference threads")
    p.add_argument(
        "--device",
        choices=DEVICES,
        default=None,
        help="where onnxruntime runs the network: cpu (default), cuda, tensorrt (the gpu extra, "
        "docs/gpu.md) or auto (cuda when it can run here, else cpu; says which); a GPU device "
        "onnxruntime cannot run here is an error, never a silent fallback",
    )
    p.add_argument(
        "--batch",
        type=int,
        default=1,
        help="windows per network call when windows run whole (--no-block-reuse, or a stride "
        "that shares no blocks); more than 1 pays on a GPU (default 1)",
    )
    p.add_argument(
        "--no-block-reuse",
        action="store_true",
        help="run the network on every window whole, even when centres share blocks (by "
        "default, with a stride that is a multiple of the block stride, each block is encoded "
        "once)",
    )
    p.add_argument(
        "--self-ensemble",
        action="store_true",
        help="for --method net: also run the network on the stream's three mirror images and "
        "average the four images (four times the time; docs/real_video.md has what it gains)",
    )
    p.add_argument("--url", help="send the work to a running service, e.g. http://127.0.0.1:8000")
    p.add_argument(
        "--png-dir", type=Path, help="also save each frame as a PNG (gamma 1/2.2), as it is done"
    )
    p.add_argument(
        "--resume",
        action="store_true",
        help="continue an interrupted run: the same command keeps the frames in "
        "OUT.npz.partial/ and reconstructs only the others",
    )
    add_progress_flags(p)


def run(args: argparse.Namespace) -> int:
    """The flags are checked where the API checks its arguments (Reconstructor, the runtime's
    ``method_window`` and ``load_network``), the output's suffix here. Frames are kept as they
    come (PNGs at once, the arrays in ``OUT.npz.partial/``, spk2img.io.frame_store), so an
    interrupted run keeps every finished frame and ``--resume`` continues it."""
    if args.out.suffix != ".npz":
        raise InputError(f"--out must name a .npz file, got {args.out}")
    if args.method == "net" and args.window != DEFAULT_TFP_WINDOW:
        raise InputError("--window is for --method tfp and tfi: net reads its model's own window")
    if args.png_dir:
        check_output_folder(args.png_dir, "--png-dir")
    spikes = api.read_spikes(args.input, args.height, args.width)
    if isinstance(spikes, DatStream) and not args.force_size:
        check_frame_size(args.input, args.height, args.width)
    if args.method == "net" and args.quality == "best":
        args.binning = _choose_binning(args, spikes)
    if args.url:
        args.no_progress = not show_progress(args)
    sources = _remote_source(args, spikes) if args.url else _local_source(args, spikes)
    with sources as source:
        store = FrameStore(args.out, _run_record(args, spikes), args.resume)
        owed = [int(k) for k in source.centers if int(k) not in store.done]
        try:
            _keep_frames(args, source, store, owed)
        except KeyboardInterrupt as exc:  # Ctrl-C or SIGTERM
            store.flush()
            say(
                args,
                f"{interrupt_message(exc)}: {store.kept} of {len(source.centers)} frames kept in "
                f"{store.dir}; the same command with --resume continues the run",
            )
            return exit_code(exc)
        except BaseException:
            store.flush()  # what is done stays done; --resume continues from it
            store.discard_if_empty()
            raise
        how = source.note()
    frames, centers = store.finish(*spikes.shape[1:])
    say(
        args,
        f"wrote {len(centers)} frames of {frames.shape[1]}x{frames.shape[2]} to {args.out}{how}",
    )
    return 0


def _keep_frames(args: argparse.Namespace, source, store: FrameStore, owed: list[int]) -> None:
    """Reconstruct the ``owed`` centres of ``source``, keeping each frame (and its PNG) as it
    comes, with a bar over the run's outputs whose ETA follows the time per output."""
    total = len(source.centers)
    with progress_bar(args, total=total) as bar:
        bar.set_description(source.label)
        bar.update(total - len(owed))
        if not owed:
            return
        resumed = len(owed) < total
        for center, image in source.frames(owed if resumed else None):
            if args.png_dir:  # first: every frame kept has its PNG
                save_png(args.png_dir, center, image)
            store.add(center, image)
            bar.update(1)


def _run_record(args: argparse.Namespace, spikes) -> dict:
    """What decides a run's frames, for ``--resume`` to check it continues the same run."""
    names = ("height", "width", "centers", "stride", "method", "window", "quality", "binning")
    names += ("model", "backend", "checkpoint", "self_ensemble", "url")
    record = {name: getattr(args, name) for name in names}
    record = {k: str(v) if isinstance(v, Path) else v for k, v in record.items()}
    return {"input": str(Path(args.input).resolve()), "frames": len(spikes), **record}


@contextmanager
def _local_source(args: argparse.Namespace, spikes: api.Spikes) -> Iterator[LocalFrames]:
    """The public API (:class:`spk2img.Reconstructor`) on ``spikes``, with its centres."""
    recon = api.Reconstructor(
        args.method,
        quality=args.quality,
        window=args.window,
        model=args.model,
        backend=args.backend,
        checkpoint=args.checkpoint,
        threads=args.threads,
        block_reuse=not args.no_block_reuse,
        device=args.device or "cpu",
        batch=args.batch,
        binning=args.binning,
        self_ensemble=args.self_ensemble,
    )
    if recon.device_note:
        say(args, recon.device_note)
    centers = recon.centers_for(len(spikes), args.centers, args.stride)
    yield LocalFrames(args, spikes, recon, centers)


@dataclass
class LocalFrames:
    """The frames of a local run: its centres, and the reconstruction of all or some."""

    args: argparse.Namespace
    spikes: api.Spikes
    recon: api.Reconstructor
    centers: np.ndarray
    """``(N,) int64``: every centre the run's arguments ask for (checked)."""

    @property
    def label(self) -> str:
        """What reconstructs, for the progress bar: the method, and the model and device."""
        network = self.recon.network
        if network is None:
            return self.args.method
        model = network.predict
        name = getattr(model, "metadata", {}).get("name") or "torch checkpoint"
        return f"{name} on {getattr(model, 'device', 'cpu')}"

    def frames(self, centers: list[int] | None = None):
        """The run's frames, or those of ``centers`` only (a resumed run), as they are done."""
        if centers is None:
            return self.recon.frames(
                self.spikes, centers=self.args.centers, stride=self.args.stride
            )
        return self.recon.frames(self.spikes, centers=centers)

    def note(self) -> str:
        """What the work came to, for the closing message."""
        where = device_note(self.recon.network.predict) if self.recon.network else ""
        return compute_note(self.recon.last_stream) + where


def parse_binning(text: str) -> int | str:
    """``--binning``: ``auto`` or an integer from 1 to :data:`MAX_BINNING`."""
    if text == "auto":
        return text
    try:
        return check_binning(int(text))
    except ValueError as exc:
        raise argparse.ArgumentTypeError(
            f"expected auto or an integer from 1 to {MAX_BINNING}, got {text!r}"
        ) from exc


def _choose_binning(args: argparse.Namespace, spikes: api.Spikes) -> int:
    """``--binning``, with ``auto`` resolved from the stream's firing rate; without the flag on
    a dim stream, a note that names the binning it would take."""
    rates = firing_rates(spikes)
    suggested = binning_for_rates(rates, len(spikes))
    if args.binning == "auto":
        say(args, f"binning {suggested} ({rates.mean():.3f} spikes/pixel/frame)")
        return suggested
    if args.binning == 1 and suggested > 1:
        say(
            args,
            f"note: a dim stream ({rates.mean():.3f} spikes/pixel/frame): "
            f"--binning {suggested} (or auto) gives the network {suggested} frames per frame",
        )
    return args.binning


def device_note(predict) -> str:
    """Where the network ran, for the closing message, when it was not the CPU."""
    provider = getattr(predict, "provider", "CPUExecutionProvider")
    return "" if provider == "CPUExecutionProvider" else f" on {predict.device} ({provider})"


def compute_note(recon) -> str:
    """What the network's work came to, for the closing message ('' for whole windows)."""
    if isinstance(recon, BlockReuseStream):
        return (
            f" (each {recon.block_frames}-frame block encoded once: {recon.blocks_encoded} blocks)"
        )
    if isinstance(recon, NetStream) and recon.binning > 1:
        return f" (binning {recon.binning}: {recon.window}-frame windows)"
    if isinstance(recon, BalancedStream) and recon.network_share:
        share = sum(recon.network_share) / len(recon.network_share)
        return f" (quality balanced: the network ran on {share:.0%} of the pixels)"
    return ""


def _remote_source(args: argparse.Namespace, spikes: api.Spikes):
    """The service at ``args.url`` (:func:`spk2img.clients.remote.remote_frames`)."""
    if args.model or args.checkpoint or args.backend != "onnx" or args.device or args.self_ensemble:
        raise InputError(
            "--url runs the service's own model: drop --model/--checkpoint/--backend/--device/"
            "--self-ensemble"
        )
    from spk2img.clients.remote import remote_frames  # the client extra

    return remote_frames(args, spikes, args.stride)


def save_png(directory: Path, center: int, image: np.ndarray) -> None:
    """Write one frame as ``frame_{centre:06d}.png`` (display gamma 1/2.2)."""
    from PIL import Image

    from spk2img.io.light import to_display

    directory.mkdir(parents=True, exist_ok=True)
    Image.fromarray(to_display(image)).save(directory / f"frame_{int(center):06d}.png")
