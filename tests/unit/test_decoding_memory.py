"""Decoding within a memory budget (issue 13 item 3), with the pixels of every image accepted before.

PNGs now decode straight to 8-bit BGR or gray (16-bit ones to 16-bit BGR or gray, scaled a
block of rows at a time); the pixels must stay those of the decode the bundled calibration was
scored with: OpenCV's ``IMREAD_UNCHANGED``, 16-bit samples scaled by ``(v + 128) // 257``,
alpha dropped, gray kept gray. ``decoded_bytes`` must bound what a decode really takes,
measured as the peak resident memory of a fresh process.
"""

from __future__ import annotations

import functools
import io
import struct
import subprocess
import sys
import zlib
from pathlib import Path

import cv2
import numpy as np
import pytest
from PIL import Image

from benchmarks.faults_clients import flat_png, png_chunk
from service.detector.images import PNG_SIGNATURE, decode_image, decoded_bytes, read_image_header
from service.errors import InvalidInput, PayloadTooLarge
from service.infra.settings import PACKAGE_ROOT, Settings
from service.serving.container import MAX_DECODED_BYTES

LIMIT = 10**8
MiB = 2**20
CHANNELS = {0: 1, 2: 3, 3: 1, 4: 2, 6: 4}
DEPTHS = {0: (1, 2, 4, 8, 16), 2: (8, 16), 3: (1, 2, 4, 8), 4: (8, 16), 6: (8, 16)}


def random_png(width: int, height: int, colour: int, depth: int, extra: bytes = b"", seed: int = 0) -> bytes:
    """A PNG of random samples in any layout, with ``extra`` chunks (tRNS, gAMA, ...) before IDAT."""
    rng = np.random.default_rng(seed)
    samples = rng.integers(0, 2**depth, (height, width * CHANNELS[colour]))
    if depth == 16:
        rows = samples.astype(">u2").view(np.uint8).reshape(height, -1)
    else:
        rows = np.packbits(
            np.unpackbits(samples.astype(np.uint8)[..., None], axis=-1)[..., 8 - depth :].reshape(height, -1),
            axis=-1,
        )
    raw = b"".join(b"\x00" + row.tobytes() for row in rows)
    entries = rng.integers(0, 256, 3 * 2**depth, dtype=np.uint8).tobytes()
    palette = png_chunk(b"PLTE", entries) if colour == 3 else b""
    header = png_chunk(b"IHDR", struct.pack(">IIBBBBB", width, height, depth, colour, 0, 0, 0))
    pixels = png_chunk(b"IDAT", zlib.compress(raw))
    return PNG_SIGNATURE + header + palette + extra + pixels + png_chunk(b"IEND", b"")


def scored_with(data: bytes) -> np.ndarray:
    """The decode the bundled calibration was scored with (OpenCV, then the old conversion)."""
    image = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_UNCHANGED)
    if image.dtype == np.uint16:
        image = ((image.astype(np.uint32) + 128) // 257).astype(np.uint8)
    if image.ndim == 2:
        return image
    if image.shape[2] in (1, 2) or read_image_header(data).channels in (1, 2):
        return np.ascontiguousarray(image[:, :, 0])
    return cv2.cvtColor(image, cv2.COLOR_BGRA2BGR) if image.shape[2] == 4 else image


def significant_bits(colour: int, depth: int) -> bytes:
    return png_chunk(b"sBIT", bytes([max(min(depth, 8) - 1, 1)] * (3 if colour == 3 else CHANNELS[colour])))


def transparency(colour: int, depth: int) -> bytes:
    if colour == 0:
        return png_chunk(b"tRNS", struct.pack(">H", 2**depth - 1))
    if colour == 2:
        return png_chunk(b"tRNS", struct.pack(">HHH", 1, 2, 3))
    if colour == 3:
        return png_chunk(b"tRNS", bytes([0, 128, 255]))
    return b""


ANCILLARY = {
    "none": lambda colour, depth: b"",
    "tRNS": transparency,
    "gAMA": lambda colour, depth: png_chunk(b"gAMA", struct.pack(">I", 90910)),
    "sBIT": significant_bits,
    "sRGB": lambda colour, depth: png_chunk(b"sRGB", b"\x00"),
}
LAYOUTS = [(c, d, a) for c, depths in DEPTHS.items() for d in depths for a in ANCILLARY]
LAYOUT_IDS = [f"type{c}-{d}bit-{a}" for c, d, a in LAYOUTS]


class TestSamePixels:
    @pytest.mark.parametrize(("colour", "depth", "ancillary"), LAYOUTS, ids=LAYOUT_IDS)
    def test_every_png_layout(self, colour: int, depth: int, ancillary: str) -> None:
        data = random_png(37, 23, colour, depth, ANCILLARY[ancillary](colour, depth))
        decoded, expected = decode_image(data, LIMIT), scored_with(data)
        assert decoded.dtype == np.uint8 and decoded.shape == expected.shape
        np.testing.assert_array_equal(decoded, expected)

    @pytest.mark.parametrize("colour", [0, 2, 4, 6])
    def test_sixteen_bit_across_scaling_blocks(self, colour: int) -> None:
        """More samples than one scaling block (2**18), every 16-bit value among them."""
        data = random_png(700, 500, colour, 16, seed=colour)
        np.testing.assert_array_equal(decode_image(data, LIMIT), scored_with(data))
        every = np.arange(65536, dtype=np.uint16).reshape(256, 256)
        ok, png = cv2.imencode(".png", every)
        assert ok
        expected = (every.astype(np.uint32) + 128) // 257
        np.testing.assert_array_equal(decode_image(png.tobytes(), LIMIT), expected)

    def test_pillow_pngs(self) -> None:
        rng = np.random.default_rng(3)
        for mode in ("RGB", "RGBA", "L", "LA", "P", "1", "I;16"):
            image = Image.fromarray(rng.integers(0, 256, (41, 29, 3), dtype=np.uint8)).convert(mode)
            buffer = io.BytesIO()
            image.save(buffer, "PNG")
            data = buffer.getvalue()
            np.testing.assert_array_equal(decode_image(data, LIMIT), scored_with(data), err_msg=mode)


class TestBudget:
    def test_the_issue_png_is_refused_before_decoding(self) -> None:
        """Issue 13: a 16-bit RGBA PNG of 6324x6324, under the pixel limit, added 1.5 GB of RSS."""
        data = flat_png(6324, 6324)
        header = read_image_header(data)
        assert header.pixels <= Settings().predict.max_image_pixels
        with pytest.raises(PayloadTooLarge) as refused:
            decode_image(data, Settings().predict.max_image_pixels, MAX_DECODED_BYTES)
        detail = refused.value.detail
        assert str(decoded_bytes(data, header)) in detail and f"of {MAX_DECODED_BYTES} bytes" in detail, (
            detail
        )
        assert "6324x6324" in detail

    def test_the_limit_is_inclusive(self) -> None:
        data = random_png(40, 30, 6, 16)
        needed = decoded_bytes(data, read_image_header(data))
        assert needed == 40 * 30 * 3 * 4
        assert decode_image(data, LIMIT, needed).shape == (30, 40, 3)
        with pytest.raises(PayloadTooLarge):
            decode_image(data, LIMIT, needed - 1)

    def test_sixteen_bit_data_shorter_than_its_header(self) -> None:
        data = random_png(300, 200, 6, 16)
        short = bytearray(data[:33])
        idat = zlib.compress(zlib.decompress(data[41 : data.index(b"IEND") - 8])[: 200 * 1000])
        short += png_chunk(b"IDAT", idat) + png_chunk(b"IEND", b"")
        with pytest.raises(InvalidInput, match=r"\(300x200\) cannot be decoded"):
            decode_image(bytes(short), LIMIT)


KINDS = (
    "jpeg-baseline",
    "jpeg-progressive-444",
    "jpeg-progressive-420",
    "jpeg-cmyk",
    "jpeg-gray",
    "png-rgb8",
    "png-rgba16",
    "png-gray16",
    "png-gray-alpha8",
)


def _jpeg(image: np.ndarray, mode: str = "RGB", **options: object) -> bytes:
    buffer = io.BytesIO()
    Image.fromarray(image).convert(mode).save(buffer, "JPEG", quality=90, **options)
    return buffer.getvalue()


@functools.cache
def measured_image(kind: str) -> bytes:
    """A 2400x1800 image of this kind (4.3 Mpx: tens of MiB decoded)."""
    photo = cv2.resize(np.random.default_rng(5).integers(0, 256, (90, 120, 3), dtype=np.uint8), (2400, 1800))
    return {
        "jpeg-baseline": lambda: _jpeg(photo),
        "jpeg-progressive-444": lambda: _jpeg(photo, progressive=True, subsampling=0),
        "jpeg-progressive-420": lambda: _jpeg(photo, progressive=True, subsampling=2),
        "jpeg-cmyk": lambda: _jpeg(photo, "CMYK"),
        "jpeg-gray": lambda: _jpeg(photo, "L"),
        "png-rgb8": lambda: cv2.imencode(".png", photo)[1].tobytes(),
        "png-rgba16": lambda: flat_png(2400, 1800),
        "png-gray16": lambda: flat_png(2400, 1800, colour_type=0),
        "png-gray-alpha8": lambda: flat_png(2400, 1800, depth=8, colour_type=4),
    }[kind]()


_MEASURE = """
import os, sys
from benchmarks.faults_clients import peak_rss_bytes, reset_peak_rss
from service.detector.images import decode_image
data = open(sys.argv[1], "rb").read()
reset_peak_rss(os.getpid())
before = peak_rss_bytes(os.getpid())
try:
    decode_image(data, 10**8, int(sys.argv[2]))
except Exception as error:
    print(type(error).__name__)
print(peak_rss_bytes(os.getpid()) - before)
"""


def peak_of_decode(tmp_path: Path, data: bytes, max_bytes: int = LIMIT) -> tuple[int, str]:
    """The rise of a fresh process's peak resident memory while it decodes ``data``, and the
    name of the error it raised ('' if none)."""
    path = tmp_path / "image"
    path.write_bytes(data)
    result = subprocess.run(
        [sys.executable, "-c", _MEASURE, str(path), str(max_bytes)],
        cwd=PACKAGE_ROOT,
        capture_output=True,
        text=True,
        timeout=60,
        check=True,
    )
    *error, peak = result.stdout.split()
    return int(peak), "".join(error)


@pytest.mark.slow
@pytest.mark.parametrize("kind", KINDS)
def test_decoded_bytes_bound_the_real_peak(tmp_path: Path, kind: str) -> None:
    data = measured_image(kind)
    header = read_image_header(data)
    assert header.pixels == 2400 * 1800
    estimate = decoded_bytes(data, header)
    peak, error = peak_of_decode(tmp_path, data)
    assert not error
    assert peak <= estimate + 4 * MiB, f"peak {peak / MiB:.1f} MiB, above the estimate {estimate / MiB:.1f}"
    assert peak >= 0.8 * estimate, f"estimate {estimate / MiB:.1f} MiB, far above the peak {peak / MiB:.1f}"


@pytest.mark.slow
def test_a_refused_image_takes_no_memory(tmp_path: Path) -> None:
    peak, error = peak_of_decode(tmp_path, flat_png(6324, 6324), MAX_DECODED_BYTES)
    assert error == "PayloadTooLarge" and peak < 4 * MiB, (error, peak)
