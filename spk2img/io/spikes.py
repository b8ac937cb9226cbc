"""Spike streams on disk and in memory (the format: docs/format.md).

On disk (PKU ``.dat``): no header; each frame is ``ceil(H*W/8)`` bytes; pixel ``p = row*W + col``
is bit ``p % 8`` (least significant bit first) of byte ``p // 8``; rows are stored bottom row
first. In memory a stream is ``(T, H, W) uint8`` of 0/1, upright, time first.
"""

from __future__ import annotations

import operator
import zipfile
from pathlib import Path

import numpy as np

from spk2img.errors import InputError

DEFAULT_HEIGHT = 250
DEFAULT_WIDTH = 400


class SpikeFormatError(InputError):
    """A byte stream or array that is not a valid spike stream of the stated size."""


def frame_nbytes(height: int, width: int) -> int:
    """Bytes one frame of ``height x width`` takes on disk: ``ceil(H*W/8)``."""
    check_size(height, width)
    return (height * width + 7) // 8


MAX_SIDE = 4096
"""The largest frame side that the commands which build frames of a size asked for (simulate,
models, export, verify) take (pixels): ten times a spike camera's. Streams read are not held to
it (the service has its own limit in pixels)."""


def check_size(height: int, width: int, max_side: int | None = None) -> None:
    """Raise :class:`SpikeFormatError` unless both sides are positive integers (and at most
    ``max_side``, when given)."""
    if int(height) != height or int(width) != width or height < 1 or width < 1:
        raise SpikeFormatError(f"height and width must be positive integers, got {height}x{width}")
    if max_side is not None and max(height, width) > max_side:
        raise SpikeFormatError(f"height and width must be at most {max_side}, got {height}x{width}")


def pack_frames(frames: np.ndarray) -> bytes:
    """Encode ``(T, H, W)`` 0/1 upright frames as ``.dat`` bytes (bottom row first, LSB first)."""
    frames = as_spike_array(frames)
    t, h, w = frames.shape
    flat = frames[:, ::-1, :].reshape(t, h * w)
    pad = frame_nbytes(h, w) * 8 - h * w
    if pad:
        flat = np.concatenate([flat, np.zeros((t, pad), np.uint8)], axis=1)
    return np.packbits(flat, axis=1, bitorder="little").tobytes()


def unpack_frames(
    data: bytes | bytearray | memoryview | np.ndarray, height: int, width: int
) -> np.ndarray:
    """Decode ``.dat`` bytes holding whole frames into ``(T, H, W) uint8`` 0/1, upright.

    Raises :class:`SpikeFormatError` for an empty buffer or one that is not a whole number of
    frames of ``height x width``.
    """
    nbytes = frame_nbytes(height, width)
    raw = np.frombuffer(data, dtype=np.uint8) if not isinstance(data, np.ndarray) else data
    raw = raw.reshape(-1)
    if raw.size == 0:
        raise SpikeFormatError("empty spike stream: no frames")
    if raw.size % nbytes:
        raise SpikeFormatError(
            f"{raw.size} bytes is not a whole number of {height}x{width} frames "
            f"({nbytes} bytes each): {raw.size // nbytes} frames and {raw.size % nbytes} "
            "bytes of a partial trailing frame"
        )
    t = raw.size // nbytes
    bits = np.unpackbits(raw.reshape(t, nbytes), axis=1, count=height * width, bitorder="little")
    return np.ascontiguousarray(bits.reshape(t, height, width)[:, ::-1, :])


def as_spike_array(frames: np.ndarray) -> np.ndarray:
    """Check and return ``frames`` as ``(T, H, W) uint8`` 0/1 (raises :class:`SpikeFormatError`)."""
    frames = np.asarray(frames)
    if frames.ndim != 3:
        raise SpikeFormatError(f"a spike array must be (T, H, W), got shape {frames.shape}")
    if frames.size == 0:
        raise SpikeFormatError(f"empty spike array of shape {frames.shape}")
    if frames.dtype == np.bool_:
        return frames.astype(np.uint8)
    if not (np.issubdtype(frames.dtype, np.integer) or np.issubdtype(frames.dtype, np.floating)):
        raise SpikeFormatError(f"spike array of dtype {frames.dtype} is not numeric")
    _check_values(frames)
    return frames if frames.dtype == np.uint8 else frames.astype(np.uint8)


CHECK_FRAMES = 256
"""Frames checked at a time by :func:`check_spike_values` (bounded memory on large files)."""


def check_spike_values(frames: np.ndarray, source: str | Path | None = None) -> np.ndarray:
    """Check that ``frames`` is a non-empty ``(T, H, W)`` array of 0/1 and return it unchanged
    (a memory-mapped array stays so: it is read :data:`CHECK_FRAMES` frames at a time).

    Raises :class:`SpikeFormatError` naming the first value that is not 0 or 1 (e.g. ``2`` or
    ``0.5``) and its frame, prefixed by ``source`` when given.
    """
    where = f"{source}: " if source is not None else ""
    if frames.ndim != 3 or frames.size == 0:
        raise SpikeFormatError(f"{where}expected a non-empty (T, H, W) array, got {frames.shape}")
    if frames.dtype == np.bool_:
        return frames
    if not np.issubdtype(frames.dtype, np.number):
        raise SpikeFormatError(f"{where}spike array of dtype {frames.dtype} is not numeric")
    for start in range(0, len(frames), CHECK_FRAMES):
        _check_values(np.asarray(frames[start : start + CHECK_FRAMES]), where, start)
    return frames


def _check_values(frames: np.ndarray, where: str = "", first: int = 0) -> None:
    """Raise :class:`SpikeFormatError` at the first value of ``frames`` that is not 0 or 1."""
    bad = frames > 1 if frames.dtype == np.uint8 else ~np.isin(frames, (0, 1))
    if bad.any():
        t, row, col = (int(i) for i in np.argwhere(bad)[0])
        value = frames[t, row, col].item()
        raise SpikeFormatError(
            f"{where}spike values must be 0 or 1, found {value!r} at frame {first + t} "
            f"(row {row}, column {col}); this is not a spike stream (docs/format.md)"
        )


class DatStream:
    """A ``.dat`` file opened memory-mapped: frames are decoded only when indexed.

    ``len(stream)`` is the frame count and ``stream.shape`` ``(T, H, W)``; ``stream[a:b]``
    returns ``(b-a, H, W) uint8`` upright and ``stream[k]`` frame ``k`` as ``(H, W)``. A
    multi-GB recording is never loaded whole, unless asked: ``np.asarray(stream)`` decodes
    every frame (``T·H·W`` bytes).
    """

    dtype = np.dtype(np.uint8)
    ndim = 3

    def __init__(self, path: str | Path, height: int = DEFAULT_HEIGHT, width: int = DEFAULT_WIDTH):
        self.path = Path(path)
        self.height, self.width = height, width
        self.frame_nbytes = frame_nbytes(height, width)
        size = self.path.stat().st_size
        if size == 0:
            raise SpikeFormatError(f"{self.path}: empty file, no frames")
        with self.path.open("rb") as file:
            head = file.read(SNIFF_BYTES)
        check_not_a_numpy_file(head, str(self.path), "give it the {kind} suffix: spk2img reads it")
        if size % self.frame_nbytes:
            raise SpikeFormatError(
                f"{self.path}: {size} bytes is not a whole number of {height}x{width} frames "
                f"({self.frame_nbytes} bytes each); wrong --height/--width or a truncated file?"
            )
        self._raw = np.memmap(self.path, dtype=np.uint8, mode="r")

    @property
    def shape(self) -> tuple[int, int, int]:
        return (len(self), self.height, self.width)

    def __len__(self) -> int:
        return self._raw.size // self.frame_nbytes

    def __array__(self, dtype=None, copy=None) -> np.ndarray:
        if copy is False:
            raise ValueError("a .dat stream is decoded into a new array: copy=False cannot hold")
        frames = self[0 : len(self)]
        return frames if dtype is None else frames.astype(dtype)

    def __getitem__(self, index: slice | int) -> np.ndarray:
        if isinstance(index, (int, np.integer)):
            frame = operator.index(index)
            if not -len(self) <= frame < len(self):
                raise IndexError(f"frame {frame} of a {len(self)}-frame stream")
            frame %= len(self)
            return self[frame : frame + 1][0]
        if not isinstance(index, slice):
            raise TypeError(
                "a DatStream takes a frame (stream[10]) or a slice of frames (stream[10:51]); "
                "np.asarray(stream) decodes them all"
            )
        start, stop, step = index.indices(len(self))
        if step != 1:
            raise TypeError("DatStream slices must be contiguous (step 1)")
        if stop <= start:
            return np.zeros((0, self.height, self.width), np.uint8)
        n = self.frame_nbytes
        return unpack_frames(self._raw[start * n : stop * n], self.height, self.width)


def read_spikes(
    path: str | Path, height: int = DEFAULT_HEIGHT, width: int = DEFAULT_WIDTH
) -> np.ndarray | DatStream:
    """Open a spike stream from ``.dat`` (memory-mapped), ``.npy`` (memory-mapped) or ``.npz``.

    ``height``/``width`` are used by ``.dat`` only. ``.npz`` files take the array under ``spk``
    or ``spikes``, else their only array. Returns something indexable by frame slices with a
    ``(T, H, W)`` shape; raises :class:`SpikeFormatError` for unreadable or malformed input and
    ``FileNotFoundError`` for a missing file.
    """
    path = Path(path)
    if path.is_dir():
        raise SpikeFormatError(f"{path} is a folder, not a spike file")
    if not path.is_file():
        raise FileNotFoundError(f"no such file: {path}")
    suffix = path.suffix.lower()
    if suffix == ".dat":
        return DatStream(path, height, width)
    if suffix in (".npy", ".npz") and path.stat().st_size == 0:
        raise SpikeFormatError(f"{path}: the file is empty")
    if suffix == ".npy":
        try:
            arr = np.load(path, mmap_mode="r", allow_pickle=False)
        except (ValueError, EOFError, OSError):
            raise SpikeFormatError(
                f"{path}: not a .npy array file (numpy.save writes one)"
            ) from None
        return _checked_array(arr, path)
    if suffix == ".npz":
        if not zipfile.is_zipfile(path):
            raise SpikeFormatError(
                f"{path}: not a .npz archive (a zip of .npy arrays, as numpy.savez writes)"
            )
        try:
            with np.load(path, allow_pickle=False) as npz:
                named = [k for k in ("spk", "spikes") if k in npz.files]
                if not named and len(npz.files) != 1:
                    raise SpikeFormatError(f"{path}: holds {npz.files}; expected a 'spk' array")
                arr = npz[(named or npz.files)[0]]
        except (ValueError, EOFError, OSError, zipfile.BadZipFile) as exc:
            raise SpikeFormatError(f"{path}: not a readable .npz archive ({exc})") from exc
        return _checked_array(arr, path)
    raise SpikeFormatError(f"{path}: unknown spike file type {suffix!r} (use .dat, .npy or .npz)")


def _checked_array(arr: np.ndarray, path: Path) -> np.ndarray:
    return check_spike_values(arr, path)  # before any work: a value of 2 or 0.5 is an error


def write_spikes(path: str | Path, frames: np.ndarray) -> None:
    """Write ``(T, H, W)`` 0/1 frames to ``.dat``, ``.npy`` or ``.npz`` (key ``spk``)."""
    path = Path(path)
    frames = as_spike_array(frames)
    suffix = path.suffix.lower()
    if suffix == ".dat":
        path.write_bytes(pack_frames(frames))
    elif suffix == ".npy":
        np.save(path, frames)
    elif suffix == ".npz":
        np.savez_compressed(path, spk=frames)
    else:
        raise SpikeFormatError(
            f"{path}: unknown spike file type {suffix!r} (use .dat, .npy or .npz)"
        )


SNIFF_BYTES = 64
"""Bytes at a stream's start that tell a numpy file sent where raw ``.dat`` bits go."""
UPLOAD_REMEDY = (
    "send the frames packed (spk2img.io.spikes.pack_frames); the Python client and "
    "'spk2img reconstruct FILE{kind} --url URL' send {kind} files packed"
)


def numpy_file_kind(head: bytes) -> str | None:
    """``".npy"`` or ``".npz"`` when ``head`` (a stream's first :data:`SNIFF_BYTES` bytes or
    all of a shorter one) is the start of such a file rather than packed spike frames, else None.

    The whole structure is checked: a ``.npy`` magic, version and the first key of its header;
    a zip entry whose name ends in ``.npy``. Packed spikes match either by chance with a
    probability under 2^-60."""
    if head[:6] == b"\x93NUMPY" and len(head) >= 20 and head[6] in (1, 2, 3) and head[7] == 0:
        start = 10 if head[6] == 1 else 12
        if head[start : start + 8] == b"{'descr'":
            return ".npy"
    if head[:4] == b"PK\x03\x04" and len(head) >= 34:
        name_length = int.from_bytes(head[26:28], "little")
        if head[30 : 30 + name_length].endswith(b".npy"):
            return ".npz"
    return None


def check_not_a_numpy_file(head: bytes, where: str, remedy: str) -> None:
    """Raise :class:`SpikeFormatError` when ``head`` starts a ``.npy`` or ``.npz`` file (its
    header would be decoded as spikes: a silent wrong answer), naming ``where`` it was met and
    the ``remedy`` (``{kind}`` in it becomes ``.npy`` or ``.npz``)."""
    kind = numpy_file_kind(head)
    if kind is not None:
        raise SpikeFormatError(
            f"{where} is a {kind} file, not the packed bits of a .dat stream (docs/format.md): "
            + remedy.format(kind=kind)
        )


class SpikeDecoder:
    """Incremental ``.dat`` decoder: feed byte chunks of any size, get whole frames back.

    >>> dec = SpikeDecoder(250, 400)
    >>> frames = dec.feed(chunk)   # (n, H, W) uint8, n >= 0
    >>> dec.finish()               # raises SpikeFormatError on a partial trailing frame
    """

    def __init__(self, height: int, width: int):
        self.height, self.width = height, width
        self.frame_nbytes = frame_nbytes(height, width)
        self._pending = bytearray()
        self._head = bytearray()  # the stream's first SNIFF_BYTES bytes, until checked
        self.frames_decoded = 0

    def feed(self, chunk: bytes | bytearray | memoryview) -> np.ndarray:
        """Add ``chunk``; return the frames it completed as ``(n, H, W) uint8`` (n may be 0).

        Raises :class:`SpikeFormatError` once the stream's first bytes are those of a ``.npy``
        or ``.npz`` file."""
        if self._head is not None:
            self._head += chunk[: SNIFF_BYTES - len(self._head)]
            if len(self._head) == SNIFF_BYTES:
                self._check_head()
        self._pending += chunk
        n_whole = len(self._pending) // self.frame_nbytes
        if n_whole == 0:
            return np.zeros((0, self.height, self.width), np.uint8)
        cut = n_whole * self.frame_nbytes
        frames = unpack_frames(bytes(self._pending[:cut]), self.height, self.width)
        del self._pending[:cut]
        self.frames_decoded += n_whole
        return frames

    def finish(self) -> None:
        """Declare the end of the stream; raise if it ended mid-frame, held no frame at all or
        was a numpy file."""
        if self._head is not None:
            self._check_head()
        if self._pending:
            raise SpikeFormatError(
                f"stream ended inside frame {self.frames_decoded}: {len(self._pending)} of "
                f"{self.frame_nbytes} bytes of a {self.height}x{self.width} frame"
            )
        if self.frames_decoded == 0:
            raise SpikeFormatError("empty spike stream: no frames")

    def _check_head(self) -> None:
        head, self._head = bytes(self._head), None
        check_not_a_numpy_file(head, "the upload", UPLOAD_REMEDY)
