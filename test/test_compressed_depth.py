"""compressed_depth_image_transport payloads: byte-level format, round trips, rejection of bad data."""

from __future__ import annotations

import struct
import subprocess
import sys
from pathlib import Path

import cv2
import numpy as np
import pytest

from hand_sog_tracker.compressed_depth import (
    HEADER_SIZE,
    decode_compressed_depth,
    encode_compressed_depth,
    parse_format,
    rvl_decode,
    rvl_encode,
    zero_invalid,
)
from hand_sog_tracker.errors import DepthImageError, InputError

REPO = Path(__file__).resolve().parents[1]


def test_invalid_depths_become_zero_in_place() -> None:
    mm = np.array([[np.nan, np.inf, -np.inf], [-1.0, 0.0, 512.5]], np.float32)
    assert zero_invalid(mm) is mm
    np.testing.assert_array_equal(mm, [[0, 0, 0], [0, 0, 512.5]])


def depth_scene(seed: int = 0, shape=(30, 40)) -> np.ndarray:
    rng = np.random.default_rng(seed)
    d = rng.uniform(200, 4000, shape).round()
    d[rng.random(shape) < 0.3] = 0  # invalid pixels in runs and alone
    d[3, :] = 0
    d[:, 7] = 0
    return d


def png16(img: np.ndarray) -> bytes:
    ok, buf = cv2.imencode(".png", img.astype(np.uint16))
    assert ok
    return buf.tobytes()


def test_16uc1_png_built_byte_by_byte_decodes_exactly() -> None:
    d = depth_scene()
    data = struct.pack("<iff", 0, 0.0, 0.0) + png16(d)  # ConfigHeader {INV_DEPTH, {0, 0}} + PNG
    out = decode_compressed_depth("16UC1; compressedDepth png", data)
    assert out.dtype == np.float32 and out.shape == d.shape
    np.testing.assert_array_equal(out, d)
    # Older publishers: "16UC1; compressedDepth" and a bare "16UC1" mean png too; mono16 = 16UC1.
    for fmt in ("16UC1; compressedDepth", "16UC1", "mono16; compressedDepth png"):
        np.testing.assert_array_equal(decode_compressed_depth(fmt, bytearray(data)), d)


def test_32fc1_png_inverse_depth_built_byte_by_byte() -> None:
    """The plugin's quantisation: A = z0 (z0 + 1), B = 1 - A / depth_max, q = uint16(A / d + B)."""
    d_m = np.array([[0.2, 0.35, 0.6], [1.0, np.nan, 9.99]], dtype=np.float32)
    z0, dmax = 100.0, 10.0
    a = np.float32(z0 * (z0 + 1.0))
    b = np.float32(1.0 - a / np.float32(dmax))
    with np.errstate(invalid="ignore"):
        q = np.where(np.isfinite(d_m), np.floor(a / d_m + b), 0).astype(np.uint16)
    data = struct.pack("<iff", 0, float(a), float(b)) + png16(q)
    out = decode_compressed_depth("32FC1; compressedDepth png", data)
    assert out[1, 1] == 0.0  # NaN -> invalid
    valid = np.isfinite(d_m)
    step_mm = d_m[valid] ** 2 / a * 1000.0  # one quantisation step at that depth
    assert np.all(np.abs(out[valid] - d_m[valid] * 1000.0) <= step_mm * 1.01)
    assert np.all(out[valid] > 0)


def test_rvl_stream_built_nibble_by_nibble() -> None:
    # Pixels 0 0 5 6: zeros=2, nonzeros=2, zigzag(5)=10 -> groups 2 then 1 (continuation on the
    # first), zigzag(1)=2; nibbles 2 2 A 1 2 padded with zeros -> one word 0x22A12000.
    words = struct.pack("<I", 0x22A12000)
    np.testing.assert_array_equal(rvl_decode(words, 4), [0, 0, 5, 6])
    assert rvl_encode(np.array([0, 0, 5, 6], np.uint16)) == words
    data = struct.pack("<iff", 0, 0.0, 0.0) + struct.pack("<II", 2, 2) + words
    np.testing.assert_array_equal(decode_compressed_depth("16UC1; compressedDepth rvl", data), [[0, 0], [5, 6]])


@pytest.mark.parametrize("codec", ["png", "rvl"])
def test_round_trips(codec: str) -> None:
    d = depth_scene(1, (48, 64))
    fmt, data = encode_compressed_depth(d, "16UC1", codec)
    assert fmt == f"16UC1; compressedDepth {codec}" and struct.unpack_from("<i", data)[0] == 0
    np.testing.assert_array_equal(decode_compressed_depth(fmt, data), d)
    fmt, data = encode_compressed_depth(d, "32FC1", codec)
    out = decode_compressed_depth(fmt, data)
    valid = d > 0
    np.testing.assert_array_equal(out > 0, valid)
    a = 100.0 * 101.0
    assert np.all(np.abs(out[valid] - d[valid]) <= (d[valid] / 1000.0) ** 2 / a * 1000.0 * 1.01 + 1e-3)


def test_rvl_handles_wrapping_deltas_and_long_runs() -> None:
    rng = np.random.default_rng(2)
    px = rng.integers(1, 65536, 5000).astype(np.uint16)
    px[100:3000] = 0
    px[-1] = 65535
    px[0] = 1
    np.testing.assert_array_equal(rvl_decode(rvl_encode(px), px.size), px)


@pytest.mark.parametrize(
    "fmt, mutate, match",
    [
        ("16UC1; compressedDepth png", lambda b: b[:HEADER_SIZE], "not more than the 12-byte header"),
        ("16UC1; compressedDepth png", lambda b: b[: len(b) // 2], "corrupt or truncated"),
        ("16UC1; compressedDepth png", lambda b: b[:HEADER_SIZE] + b"JFIF" + b[HEADER_SIZE + 4 :], "not a PNG"),
        ("16UC1; compressedDepth png", lambda b: struct.pack("<i", -1) + b[4:], "compressionFormat -1"),
        ("16UC1; compressedDepth rvl", lambda b: b[: len(b) - 8], "truncated"),
        ("16UC1; compressedDepth rvl", lambda b: b[:-1], "multiple of 4"),
        (
            "16UC1; compressedDepth rvl",
            lambda b: b[:HEADER_SIZE] + struct.pack("<II", 0, 5) + b[HEADER_SIZE + 8 :],
            "zero size",
        ),
        (
            "16UC1; compressedDepth rvl",
            lambda b: b[:HEADER_SIZE] + struct.pack("<II", 9000, 9000) + b[HEADER_SIZE + 8 :],
            "more than max_image_pixels",
        ),
        (
            "32FC1; compressedDepth png",
            lambda b: b[:4] + struct.pack("<ff", 0.0, 0.0) + b[HEADER_SIZE:],
            "quantisation",
        ),
        ("16UC1; compressed jpeg", lambda b: b, "unsupported compressed depth format"),
        ("bgr8; compressedDepth png", lambda b: b, "unsupported encoding"),
    ],
)
def test_bad_payloads_are_rejected_with_a_reason(fmt: str, mutate, match: str) -> None:
    enc = fmt.split(";")[0]
    codec = "rvl" if fmt.endswith("rvl") else "png"
    _, data = encode_compressed_depth(depth_scene(3), "32FC1" if enc == "32FC1" else "16UC1", codec)
    with pytest.raises(DepthImageError, match=match) as info:
        decode_compressed_depth(fmt, mutate(data))
    assert isinstance(info.value, InputError)


def test_sparse_rvl_is_accepted_and_data_after_the_image_is_corrupt() -> None:
    """Valid streams are accepted however well they compress (a hand on an empty background,
    87% zeros); a stream with more after its image's last code is not."""
    d = np.zeros((240, 320), np.float32)
    d[100:140, 150:180] = 450.0 + np.arange(30)
    fmt, data = encode_compressed_depth(d, "16UC1", "rvl")
    assert (d.size / (len(data) - HEADER_SIZE - 8)) > 5  # the ratio the old bound rejected
    np.testing.assert_array_equal(decode_compressed_depth(fmt, data), d)
    zeros = encode_compressed_depth(np.zeros((240, 320)), "16UC1", "rvl")[1]
    assert not decode_compressed_depth(fmt, zeros).any()
    for extra in (rvl_encode(np.array([7, 8], np.uint16)), b"\0\0\0\0" * 2):
        with pytest.raises(DepthImageError, match="follow the image"):
            decode_compressed_depth(fmt, data + extra)


def test_declared_sizes_are_checked_before_decoding() -> None:
    """A small PNG of a huge image (zeros compress well) is refused from its IHDR."""
    import cv2

    big = cv2.imencode(".png", np.zeros((4000, 4000), np.uint16))[1].tobytes()
    data = struct.pack("<iff", 0, 0.0, 0.0) + big
    assert len(data) < 200_000
    with pytest.raises(DepthImageError, match="4000x4000 = 16000000 pixels, more than max_image_pixels"):
        decode_compressed_depth("16UC1; compressedDepth png", data)
    assert decode_compressed_depth("16UC1; compressedDepth png", data, max_pixels=None).shape == (4000, 4000)
    grey8 = struct.pack("<iff", 0, 0.0, 0.0) + cv2.imencode(".png", np.zeros((8, 8), np.uint8))[1].tobytes()
    with pytest.raises(DepthImageError, match="bit depth 8"):
        decode_compressed_depth("16UC1; compressedDepth png", grey8)


def test_rvl_run_past_the_image_is_corrupt() -> None:
    words = rvl_encode(np.array([0, 0, 5, 6], np.uint16))
    with pytest.raises(DepthImageError, match="past the image"):
        rvl_decode(words, 3)


def test_colour_png_is_rejected() -> None:
    ok, buf = cv2.imencode(".png", np.zeros((4, 4, 3), np.uint8))
    with pytest.raises(DepthImageError, match="single-channel 16-bit"):
        decode_compressed_depth("16UC1; compressedDepth png", bytes(12) + buf.tobytes())


def test_module_needs_no_ros() -> None:
    code = (
        "import sys, hand_sog_tracker.compressed_depth, hand_sog_tracker.core.urdf\n"
        "bad = sorted(m for m in sys.modules if m.split('.')[0] in ('rclpy', 'rosbags', 'sensor_msgs'))\n"
        "assert not bad, bad\n"
    )
    out = subprocess.run([sys.executable, "-c", code], cwd=REPO, capture_output=True, text=True, timeout=60)
    assert out.returncode == 0, out.stderr


def test_parse_format() -> None:
    assert parse_format("32FC1; compressedDepth rvl").codec == "rvl"
    assert parse_format(" 16UC1 ;compressedDepth png ").encoding == "16UC1"
