"""Image header parsing and decoding of untrusted bytes (real JPEG/PNG files from OpenCV)."""

from __future__ import annotations

import struct
import zlib

import cv2
import numpy as np
import pytest

from service import image_decoding
from service.errors import InvalidInput, PayloadTooLarge, UnsupportedMediaType
from service.image_decoding import ImageHeader, decode_image, read_image_header

LIMIT = 10_000_000


def encode(ext: str, image: np.ndarray, *params: int) -> bytes:
    ok, buf = cv2.imencode(ext, image, list(params))
    assert ok
    return buf.tobytes()


def colour(h: int = 30, w: int = 40) -> np.ndarray:
    rng = np.random.default_rng(0)
    return rng.integers(0, 256, (h, w, 3), dtype=np.uint8)


def png_chunk(kind: bytes, payload: bytes) -> bytes:
    return struct.pack(">I", len(payload)) + kind + payload + struct.pack(">I", zlib.crc32(kind + payload))


def handmade_png(width: int, height: int, colour_type: int, depth: int, rows: bytes) -> bytes:
    """A minimal PNG (for layouts OpenCV cannot write, e.g. gray + alpha)."""
    ihdr = struct.pack(">IIBBBBB", width, height, depth, colour_type, 0, 0, 0)
    return (
        image_decoding.PNG_SIGNATURE
        + png_chunk(b"IHDR", ihdr)
        + png_chunk(b"IDAT", zlib.compress(rows))
        + png_chunk(b"IEND", b"")
    )


def patch_png_size(data: bytes, width: int, height: int) -> bytes:
    ihdr = bytearray(data[12:29])
    ihdr[4:12] = struct.pack(">II", width, height)
    return data[:12] + bytes(ihdr) + struct.pack(">I", zlib.crc32(bytes(ihdr))) + data[33:]


def sof_offset(data: bytes) -> int:
    """Offset of the SOFn marker in an OpenCV-written JPEG."""
    for marker in (b"\xff\xc0", b"\xff\xc1", b"\xff\xc2"):
        pos = data.find(marker)
        if pos > 0:
            return pos
    raise AssertionError("no SOF")


def patch_jpeg_size(data: bytes, width: int, height: int) -> bytes:
    pos = sof_offset(data) + 5  # marker (2), length (2), precision (1)
    return data[:pos] + struct.pack(">HH", height, width) + data[pos + 4 :]


def insert_after_soi(data: bytes, extra: bytes) -> bytes:
    return data[:2] + extra + data[2:]


@pytest.fixture
def no_decoder(monkeypatch: pytest.MonkeyPatch) -> None:
    """Fail the test if pixels would be decoded."""

    def refuse(*_args: object) -> None:
        raise AssertionError("cv2.imdecode must not be called")

    monkeypatch.setattr(image_decoding.cv2, "imdecode", refuse)


class TestHeader:
    @pytest.mark.parametrize(
        ("params", "sof"),
        [((), 0xC0), ((cv2.IMWRITE_JPEG_PROGRESSIVE, 1), 0xC2), ((cv2.IMWRITE_JPEG_RST_INTERVAL, 1), 0xC0)],
        ids=["baseline", "progressive", "restart-interval"],
    )
    def test_jpeg_variants(self, params: tuple[int, ...], sof: int) -> None:
        data = encode(".jpg", colour(30, 40), *params)
        assert data[sof_offset(data) + 1] == sof
        assert read_image_header(data) == ImageHeader("jpeg", 40, 30, 3)

    def test_gray_jpeg(self) -> None:
        data = encode(".jpg", colour()[:, :, 0])
        assert read_image_header(data) == ImageHeader("jpeg", 40, 30, 1)

    @pytest.mark.parametrize(
        ("image", "channels"),
        [
            (colour(), 3),
            (colour()[:, :, 0], 1),
            (np.dstack([colour(), colour()[:, :, :1]]), 4),
            (colour().astype(np.uint16) * 257, 3),
        ],
        ids=["rgb", "gray", "rgba", "rgb16"],
    )
    def test_png_variants(self, image: np.ndarray, channels: int) -> None:
        assert read_image_header(encode(".png", image)) == ImageHeader("png", 40, 30, channels)

    def test_jpeg_fill_bytes_and_standalone_markers_are_skipped(self) -> None:
        data = encode(".jpg", colour())
        data = insert_after_soi(data, b"\xff\xd0" + b"\xff\x01" + b"\xff\xff\xff")
        assert read_image_header(data) == ImageHeader("jpeg", 40, 30, 3)
        assert decode_image(data, LIMIT).shape == (30, 40, 3)

    def test_jpeg_large_segments_before_the_frame_header(self) -> None:
        comment = b"\xff\xfe" + struct.pack(">H", 65535) + b"\xff" * 65533  # 0xFF inside a payload
        data = insert_after_soi(encode(".jpg", colour()), comment * 3)
        assert read_image_header(data) == ImageHeader("jpeg", 40, 30, 3)

    def test_only_the_header_bytes_are_needed(self) -> None:
        data = encode(".jpg", colour())
        assert read_image_header(data[: sof_offset(data) + 12]).width == 40
        assert read_image_header(encode(".png", colour())[:33]).height == 30

    @pytest.mark.parametrize("cut", [2, 3, 5, 20])
    def test_truncated_jpeg_header(self, cut: int) -> None:
        with pytest.raises(InvalidInput, match="JPEG image is truncated"):
            read_image_header(encode(".jpg", colour())[:cut])

    @pytest.mark.parametrize("cut", [8, 20, 32])
    def test_truncated_png_header(self, cut: int) -> None:
        with pytest.raises(InvalidInput, match="PNG image is truncated"):
            read_image_header(encode(".png", colour())[:cut])

    def test_png_header_crc_is_checked(self) -> None:
        data = bytearray(encode(".png", colour()))
        data[17] ^= 0x01
        with pytest.raises(InvalidInput, match="CRC"):
            read_image_header(bytes(data))

    def test_png_zero_size(self) -> None:
        with pytest.raises(InvalidInput, match="invalid size 0x30"):
            read_image_header(patch_png_size(encode(".png", colour()), 0, 30))

    def test_jpeg_zero_height_dnl(self) -> None:
        with pytest.raises(InvalidInput, match="DNL"):
            read_image_header(patch_jpeg_size(encode(".jpg", colour()), 40, 0))

    def test_jpeg_scan_before_frame_header(self) -> None:
        data = insert_after_soi(encode(".jpg", colour()), b"\xff\xda\x00\x02")
        with pytest.raises(InvalidInput, match=r"scan data \(SOS\) before the frame header"):
            read_image_header(data)

    def test_jpeg_end_before_frame_header(self) -> None:
        with pytest.raises(InvalidInput, match="EOI"):
            read_image_header(b"\xff\xd8\xff\xd9")

    def test_jpeg_bad_segment_length(self) -> None:
        with pytest.raises(InvalidInput, match="length 1"):
            read_image_header(b"\xff\xd8\xff\xe0\x00\x01rest")

    def test_empty(self) -> None:
        with pytest.raises(InvalidInput, match="empty"):
            read_image_header(b"")

    @pytest.mark.parametrize(
        ("data", "name"),
        [
            (b"GIF89a\x01\x00\x01\x00", "GIF"),
            (b"RIFF\x00\x00\x00\x00WEBPVP8 ", "WebP"),
            (b"%PDF-1.7", "not a recognised image format"),
        ],
    )
    def test_other_formats_are_unsupported(self, data: bytes, name: str) -> None:
        with pytest.raises(UnsupportedMediaType, match=name) as info:
            read_image_header(data)
        assert "only JPEG or PNG" in info.value.detail

    def test_real_bmp_is_unsupported(self) -> None:
        with pytest.raises(UnsupportedMediaType, match="BMP"):
            decode_image(encode(".bmp", colour()), LIMIT)


class TestDecode:
    def test_colour_jpeg_is_bgr(self) -> None:
        image = np.zeros((32, 48, 3), np.uint8)
        image[:, :16] = (255, 0, 0)  # blue, in OpenCV's BGR order
        image[:, 16:32] = (0, 255, 0)
        image[:, 32:] = (0, 0, 255)
        decoded = decode_image(encode(".jpg", image, cv2.IMWRITE_JPEG_QUALITY, 100), LIMIT)
        assert decoded.dtype == np.uint8 and decoded.shape == (32, 48, 3)
        assert np.abs(decoded.astype(int) - image).mean() < 8

    def test_colour_png_is_exact(self) -> None:
        image = colour()
        np.testing.assert_array_equal(decode_image(encode(".png", image), LIMIT), image)

    def test_gray_stays_two_dimensional(self) -> None:
        gray = colour()[:, :, 0]
        np.testing.assert_array_equal(decode_image(encode(".png", gray), LIMIT), gray)
        assert decode_image(encode(".jpg", gray), LIMIT).shape == (30, 40)

    def test_alpha_is_dropped(self) -> None:
        image = colour()
        rgba = np.dstack([image, np.full((30, 40), 7, np.uint8)])
        np.testing.assert_array_equal(decode_image(encode(".png", rgba), LIMIT), image)

    def test_gray_alpha_png_becomes_gray(self) -> None:
        rows = b"".join(b"\x00" + bytes([v, 255 - v] * 4) for v in (10, 20, 30))
        decoded = decode_image(handmade_png(4, 3, colour_type=4, depth=8, rows=rows), LIMIT)
        assert decoded.shape == (3, 4)
        np.testing.assert_array_equal(decoded[:, 0], [10, 20, 30])

    def test_sixteen_bit_is_scaled_to_eight(self) -> None:
        values = np.array([[0, 257, 65535, 32896]], dtype=np.uint16)
        decoded = decode_image(encode(".png", values), LIMIT)
        assert decoded.dtype == np.uint8
        np.testing.assert_array_equal(decoded, [[0, 1, 255, 128]])

    def test_sixteen_bit_colour(self) -> None:
        image = colour()
        decoded = decode_image(encode(".png", image.astype(np.uint16) * 257), LIMIT)
        np.testing.assert_array_equal(decoded, image)

    @pytest.mark.parametrize("ext", [".jpg", ".png"])
    def test_oversize_is_refused_before_decoding(self, ext: str, no_decoder: None) -> None:
        data = encode(ext, colour())
        patched = patch_png_size(data, 60000, 50000) if ext == ".png" else patch_jpeg_size(data, 60000, 50000)
        with pytest.raises(PayloadTooLarge) as info:
            decode_image(patched, LIMIT)
        message = info.value.detail
        assert "60000x50000" in message and str(LIMIT) in message and "CKS_MAX_IMAGE_PIXELS" in message

    def test_limit_is_inclusive(self) -> None:
        assert decode_image(encode(".png", colour()), 1200).shape == (30, 40, 3)
        with pytest.raises(PayloadTooLarge):
            decode_image(encode(".png", colour()), 1199)

    @pytest.mark.parametrize("ext", [".jpg", ".png"])
    def test_truncated_pixel_data(self, ext: str) -> None:
        data = encode(ext, colour(120, 160))
        with pytest.raises(InvalidInput, match="cannot be decoded"):
            decode_image(data[: len(data) * 2 // 3], LIMIT)

    def test_progressive_jpeg_truncated_between_scans(self) -> None:
        data = encode(".jpg", colour(120, 160), cv2.IMWRITE_JPEG_PROGRESSIVE, 1)
        second_scan = data.find(b"\xff\xda", data.find(b"\xff\xda") + 2)
        with pytest.raises(InvalidInput, match="truncated"):
            decode_image(data[:second_scan], LIMIT)

    def test_corrupt_png_data(self) -> None:
        data = bytearray(encode(".png", colour(120, 160)))
        idat = data.find(b"IDAT")
        data[idat + 20 : idat + 60] = b"\x00" * 40
        with pytest.raises(InvalidInput, match="PNG image \\(160x120\\) cannot be decoded"):
            decode_image(bytes(data), LIMIT)

    def test_header_only_jpeg(self) -> None:
        data = encode(".jpg", colour())
        with pytest.raises(InvalidInput, match="cannot be decoded"):
            decode_image(data[: data.find(b"\xff\xda")], LIMIT)
