import io

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from reference import encode_dat

from spk2img.io.spikes import (
    DatStream,
    SpikeDecoder,
    SpikeFormatError,
    frame_nbytes,
    numpy_file_kind,
    pack_frames,
    read_spikes,
    unpack_frames,
    write_spikes,
)


@st.composite
def spike_arrays(draw, max_t=5, max_side=19):
    t = draw(st.integers(1, max_t))
    h = draw(st.integers(1, max_side))
    w = draw(st.integers(1, max_side))
    seed = draw(st.integers(0, 2**31))
    p = draw(st.sampled_from([0.0, 0.1, 0.5, 1.0]))
    return (np.random.default_rng(seed).random((t, h, w)) < p).astype(np.uint8)


def test_hand_made_fixture_pins_bit_order_and_flip():
    # 2x4 frame: the only spike is at the upright top-left pixel (row 0, col 0).
    frame = np.zeros((1, 2, 4), np.uint8)
    frame[0, 0, 0] = 1
    # Stored bottom row first, so upright row 0 is stored row 1: p = 1*4 + 0 = 4 -> bit 4 of byte 0.
    assert pack_frames(frame) == bytes([0b0001_0000])
    # The upright bottom-right pixel (row 1, col 3) is stored row 0, p = 3 -> bit 3.
    frame = np.zeros((1, 2, 4), np.uint8)
    frame[0, 1, 3] = 1
    assert pack_frames(frame) == bytes([0b0000_1000])
    # MSB-first decoding or a missing flip would put the spike elsewhere.
    decoded = unpack_frames(bytes([0b0000_0001]), 2, 4)
    assert decoded[0, 1, 0] == 1 and decoded.sum() == 1


def test_partial_last_byte_is_zero_padded():
    frames = np.ones((2, 3, 3), np.uint8)  # 9 pixels -> 2 bytes, 7 unused bits
    data = pack_frames(frames)
    assert len(data) == 2 * frame_nbytes(3, 3) == 4
    assert data[1] == 0b0000_0001 and data[3] == 0b0000_0001


@settings(max_examples=60, deadline=None)
@given(spike_arrays())
def test_pack_matches_independent_encoder_and_round_trips(frames):
    data = pack_frames(frames)
    assert data == encode_dat(frames)
    np.testing.assert_array_equal(unpack_frames(data, *frames.shape[1:]), frames)


@settings(max_examples=60, deadline=None)
@given(spike_arrays(max_t=6), st.data())
def test_decoding_is_identical_for_every_chunking(frames, data):
    raw = pack_frames(frames)
    cuts = sorted(data.draw(st.lists(st.integers(0, len(raw)), max_size=8)))
    pieces = [raw[a:b] for a, b in zip([0, *cuts], [*cuts, len(raw)], strict=True)]
    dec = SpikeDecoder(*frames.shape[1:])
    got = [f for piece in pieces for f in dec.feed(piece)]
    dec.finish()
    np.testing.assert_array_equal(np.stack(got), frames)


def _numpy_file(array: np.ndarray, kind: str, key: str) -> bytes:
    buffer = io.BytesIO()
    if kind == ".npy":
        np.save(buffer, array)
    else:
        (np.savez if key == "arr" else np.savez_compressed)(buffer, **{key: array})
    return buffer.getvalue()


@settings(max_examples=40, deadline=None)
@given(
    spike_arrays(max_t=50),
    st.sampled_from(["u1", "bool", "f4", ">i8"]),
    st.sampled_from([".npy", ".npz"]),
    st.sampled_from(["spk", "arr", "a_long_array_name"]),
    st.data(),
)
def test_a_numpy_file_sent_as_dat_bits_is_named_never_decoded(frames, dtype, kind, key, data):
    """Whatever array, dtype and key a ``.npy`` or ``.npz`` holds, its first bytes name it, in
    any chunking of an upload and as a file called ``.dat``; packed spikes never match."""
    content = _numpy_file(frames.astype(dtype), kind, key)
    assert numpy_file_kind(content[:64]) == kind
    assert numpy_file_kind(pack_frames(frames)[:64]) is None
    height, width = data.draw(st.sampled_from([(1, 8), (4, 4), (16, 24), (250, 400)]))
    cuts = sorted(data.draw(st.lists(st.integers(0, len(content)), max_size=6)))
    decoder = SpikeDecoder(height, width)
    with pytest.raises(SpikeFormatError, match=rf"the upload is a \{kind} file"):
        for a, b in zip([0, *cuts], [*cuts, len(content)], strict=True):
            decoder.feed(content[a:b])
        decoder.finish()


def test_a_numpy_file_named_dat_is_named(tmp_path, capsys):
    from spk2img.cli import main

    path = tmp_path / "s.dat"
    path.write_bytes(_numpy_file(np.zeros((100, 16, 16), np.uint8), ".npz", "spk"))
    args = [
        "reconstruct",
        str(path),
        "--height",
        "16",
        "--width",
        "16",
        "--out",
        str(tmp_path / "o.npz"),
    ]
    assert main([*args, "--method", "tfp"]) == 2
    err = capsys.readouterr().err
    assert "is a .npz file, not the packed bits" in err and "give it the .npz suffix" in err


@settings(max_examples=25, deadline=None)
@given(spike_arrays(), st.sampled_from([".dat", ".npy", ".npz"]))
def test_file_round_trip(tmp_path_factory, frames, suffix):
    path = tmp_path_factory.mktemp("rt") / f"s{suffix}"
    write_spikes(path, frames)
    back = read_spikes(path, *frames.shape[1:])
    np.testing.assert_array_equal(np.asarray(back[0 : len(frames)]), frames)


def test_dat_is_memory_mapped_and_sliced(tmp_path):
    frames = (np.random.default_rng(1).random((50, 7, 9)) < 0.4).astype(np.uint8)
    path = tmp_path / "s.dat"
    write_spikes(path, frames)
    stream = read_spikes(path, 7, 9)
    assert isinstance(stream, DatStream) and isinstance(stream._raw, np.memmap)
    assert stream.shape == (50, 7, 9)
    np.testing.assert_array_equal(stream[13:27], frames[13:27])


def test_errors_are_clear(tmp_path):
    with pytest.raises(SpikeFormatError, match="partial trailing frame"):
        unpack_frames(bytes(7), 4, 4)  # 2-byte frames
    with pytest.raises(SpikeFormatError, match="empty"):
        unpack_frames(b"", 4, 4)
    dec = SpikeDecoder(4, 4)
    dec.feed(bytes(3))
    with pytest.raises(SpikeFormatError, match="inside frame 1"):
        dec.finish()
    with pytest.raises(SpikeFormatError, match="empty"):
        SpikeDecoder(4, 4).finish()
    path = tmp_path / "x.dat"
    path.write_bytes(bytes(12_500 * 2 + 1))
    with pytest.raises(SpikeFormatError, match="not a whole number"):
        read_spikes(path)
    (tmp_path / "e.dat").write_bytes(b"")
    with pytest.raises(SpikeFormatError, match="empty"):
        read_spikes(tmp_path / "e.dat")
    with pytest.raises(SpikeFormatError, match="height and width"):
        frame_nbytes(0, 5)
    with pytest.raises(FileNotFoundError):
        read_spikes(tmp_path / "missing.dat")
    with pytest.raises(SpikeFormatError, match="0 or 1"):
        write_spikes(tmp_path / "bad.npy", np.full((2, 3, 3), 2))


@pytest.mark.parametrize(
    ("name", "content", "words"),
    [
        ("empty.npy", b"", "the file is empty"),
        ("empty.npz", b"", "the file is empty"),
        ("text.npz", b"frame 1: 0 1 1 0\n", "not a .npz archive"),
        ("text.npy", b"frame 1: 0 1 1 0\n", "not a .npy array file"),
    ],
)
def test_empty_or_foreign_files_get_one_line_and_exit_2(tmp_path, capsys, name, content, words):
    from spk2img.cli import main

    path = tmp_path / name
    path.write_bytes(content)
    with pytest.raises(SpikeFormatError, match=words):
        read_spikes(path)
    assert main(["reconstruct", str(path), "--out", str(tmp_path / "o.npz"), "--no-progress"]) == 2
    err = capsys.readouterr().err.strip()
    assert words in err and "\n" not in err and "pickle" not in err and "Traceback" not in err


def test_a_dat_stream_behaves_like_the_array_it_holds(tmp_path):
    """``np.asarray``, ``len``, ``shape``, ``dtype``, a frame and a slice: what a user does with
    the ``(T, H, W)`` array the docs promise, without decoding more than asked."""
    frames = (np.random.default_rng(4).random((9, 5, 16)) < 0.4).astype(np.uint8)
    path = tmp_path / "s.dat"
    write_spikes(path, frames)
    stream = read_spikes(path, 5, 16)
    assert isinstance(stream, DatStream)
    assert len(stream) == 9 and stream.shape == (9, 5, 16) and stream.ndim == 3
    assert np.array_equal(np.asarray(stream), frames) and np.asarray(stream).dtype == stream.dtype
    assert np.asarray(stream, dtype=np.float32).dtype == np.float32
    assert np.array_equal(stream[3], frames[3]) and np.array_equal(stream[-1], frames[-1])
    assert np.array_equal(stream[2:5], frames[2:5])
    with pytest.raises(IndexError, match="frame 9 of a 9-frame stream"):
        stream[9]
    with pytest.raises(TypeError, match="np.asarray"):
        stream[[1, 2]]
    with pytest.raises(ValueError, match="copy=False"):
        np.asarray(stream, copy=False)
