"""The response framing of ``POST /v1/reconstruct`` (media type ``application/x-spk2img-frames``).

A response body is a sequence of records; any language can parse it::

    record  := tag (4 ASCII bytes) | length (uint32, little-endian) | payload (length bytes)
    "FRAM"  payload := centre (int64 LE) | height (uint32 LE) | width (uint32 LE)
                       | format (4 ASCII bytes: "f32 ", "u8  " or "png ") | data
            data    := "f32 ": height*width float32 LE, row-major, upright, linear [0, 1]
                       "u8  ": height*width uint8, row-major, upright (display values)
                       "png ": a PNG file (8-bit greyscale)
    "ERRO"  payload := UTF-8 JSON {"detail": str, "status": int} — an error found after the
                       response started (e.g. the upload ended mid-frame); nothing follows it
    "DONE"  payload := UTF-8 JSON {"frames": int} — the stream ended cleanly

Frames come in ascending centre order; a well-formed response ends with exactly one of
``DONE`` or ``ERRO``.
"""

from __future__ import annotations

import json
import struct
from dataclasses import dataclass

import numpy as np

MEDIA_TYPE = "application/x-spk2img-frames"
FORMATS = {"float32": b"f32 ", "uint8": b"u8  ", "png": b"png "}
_HEAD = struct.Struct("<4sI")
_FRAME_HEAD = struct.Struct("<qII4s")


class FramingError(ValueError):
    """A response body that does not follow the framing."""


@dataclass(frozen=True)
class FrameRecord:
    center: int
    image: np.ndarray  # (H, W) float32 for "f32 ", (H, W) uint8 for "u8 " and "png "
    format: str


@dataclass(frozen=True)
class ErrorRecord:
    detail: str
    status: int


@dataclass(frozen=True)
class DoneRecord:
    frames: int


Record = FrameRecord | ErrorRecord | DoneRecord


def _record(tag: bytes, payload: bytes) -> bytes:
    return _HEAD.pack(tag, len(payload)) + payload


def encode_frame(
    center: int, image: np.ndarray, fmt: str = "float32", data: bytes | None = None
) -> bytes:
    """One ``FRAM`` record. ``image`` is ``(H, W)``; ``data`` is the PNG bytes for ``png``."""
    h, w = image.shape
    if fmt == "float32":
        data = np.ascontiguousarray(image, "<f4").tobytes()
    elif fmt == "uint8":
        data = np.ascontiguousarray(image, np.uint8).tobytes()
    elif data is None:
        raise ValueError("png frames need their encoded bytes")
    return _record(b"FRAM", _FRAME_HEAD.pack(int(center), h, w, FORMATS[fmt]) + data)


def encode_error(detail: str, status: int) -> bytes:
    return _record(b"ERRO", json.dumps({"detail": detail, "status": status}).encode())


def encode_done(frames: int) -> bytes:
    return _record(b"DONE", json.dumps({"frames": frames}).encode())


class RecordParser:
    """Incremental parser: :meth:`feed` bytes of any size, get whole records back."""

    def __init__(self):
        self._buf = bytearray()

    def feed(self, chunk: bytes) -> list[Record]:
        self._buf += chunk
        records = []
        while len(self._buf) >= _HEAD.size:
            tag, length = _HEAD.unpack_from(self._buf)
            if len(self._buf) < _HEAD.size + length:
                break
            payload = bytearray(self._buf[_HEAD.size : _HEAD.size + length])  # writable frames
            del self._buf[: _HEAD.size + length]
            records.append(_decode(tag, payload))
        return records

    def finish(self) -> None:
        if self._buf:
            raise FramingError(f"response ended inside a record ({len(self._buf)} bytes left)")


def _decode(tag: bytes, payload: bytes) -> Record:
    if tag == b"FRAM":
        center, h, w, fmt = _FRAME_HEAD.unpack_from(payload)
        data = payload[_FRAME_HEAD.size :]
        if fmt == FORMATS["float32"]:
            return FrameRecord(center, np.frombuffer(data, "<f4").reshape(h, w), "float32")
        if fmt == FORMATS["uint8"]:
            return FrameRecord(center, np.frombuffer(data, np.uint8).reshape(h, w), "uint8")
        if fmt == FORMATS["png"]:
            import io

            from PIL import Image

            return FrameRecord(center, np.asarray(Image.open(io.BytesIO(data))), "png")
        raise FramingError(f"unknown frame format {fmt!r}")
    if tag == b"ERRO":
        body = json.loads(payload)
        return ErrorRecord(str(body.get("detail", "")), int(body.get("status", 500)))
    if tag == b"DONE":
        return DoneRecord(int(json.loads(payload)["frames"]))
    raise FramingError(f"unknown record tag {tag!r}")
