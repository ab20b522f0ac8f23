"""Image header parsing and decoding of untrusted bytes (real JPEG/PNG files from OpenCV and Pillow).

Strict decoding (issue 12 item 4, issue 13 item 3): corrupt or truncated data is
``InvalidInput``; valid files decode to exactly OpenCV's ``imdecode(IMREAD_UNCHANGED)``
pixels, the decoder the bundled calibration was scored with.
"""

from __future__ import annotations

import hashlib
import io
import itertools
import struct
import zlib

import cv2
import numpy as np
import pytest
from PIL import Image

from service.detector import images as image_decoding
from service.detector.images import ImageHeader, decode_image, read_image_header
from service.errors import InvalidInput, PayloadTooLarge, UnsupportedMediaType
from service.infra.settings import DEFAULT_MODEL_DIR

LIMIT = 10_000_000
SAMPLES = sorted((DEFAULT_MODEL_DIR / "samples" / "images").glob("*.jpg"))
# sha256 over (name, shape, pixels) of every sample as OpenCV 5.0.0 (libjpeg-turbo 3.1.2)
# decoded it when the bundled calibration was in use: a decoder or library update that
# moves a single pixel fails here, because calibration and prediction must see the same pixels.
SAMPLES_DIGEST = "62d86197b04f35b87b4bee9319dd66f5189454e2a9bdf4c96f144ffca89e339c"


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


def opencv(data: bytes) -> np.ndarray:
    """Today's reference decode: the pixels the bundled calibration was scored from."""
    image = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_UNCHANGED)
    assert image is not None
    return image


def sample_jpeg() -> bytes:
    return SAMPLES[0].read_bytes()


def scan_data(data: bytes) -> tuple[int, int]:
    """(start, end) of the entropy-coded data of a single-scan JPEG; end is the EOI's offset."""
    sos = data.find(b"\xff\xda")
    (length,) = struct.unpack(">H", data[sos + 2 : sos + 4])
    return sos + 2 + length, data.rfind(b"\xff\xd9")


def garbage_in_scan(data: bytes, seed: int, size: int = 4000) -> bytes:
    """Random bytes over the middle of the scan data; headers and EOI intact."""
    start, end = scan_data(data)
    middle = (start + end) // 2
    noise = np.random.default_rng(seed).integers(0, 256, size, dtype=np.uint8).tobytes()
    return data[:middle] + noise + data[middle + size :]


def pil_jpeg(image: np.ndarray, mode: str = "RGB", **options: object) -> bytes:
    buffer = io.BytesIO()
    Image.fromarray(image[:, :, ::-1] if image.ndim == 3 else image).convert(mode).save(
        buffer, "JPEG", **options
    )
    return buffer.getvalue()


def png_chunks(data: bytes) -> list[tuple[bytes, bytes]]:
    """(type, payload) of every chunk of a well-formed PNG."""
    chunks, pos = [], 8
    while pos < len(data):
        (length,) = struct.unpack(">I", data[pos : pos + 4])
        chunks.append((data[pos + 4 : pos + 8], data[pos + 8 : pos + 8 + length]))
        pos += 12 + length
    return chunks


def build_png(chunks: list[tuple[bytes, bytes]]) -> bytes:
    return image_decoding.PNG_SIGNATURE + b"".join(png_chunk(kind, payload) for kind, payload in chunks)


def with_bad_crc(data: bytes, kind: bytes, index: int = 0) -> bytes:
    """The ``index``-th chunk of type ``kind`` with its CRC inverted, its payload untouched."""
    pos, seen = 8, 0
    while True:
        (length,) = struct.unpack(">I", data[pos : pos + 4])
        if data[pos + 4 : pos + 8] == kind:
            if seen == index:
                crc_at = pos + 8 + length
                return data[:crc_at] + bytes(b ^ 0xFF for b in data[crc_at : crc_at + 4]) + data[crc_at + 4 :]
            seen += 1
        pos += 12 + length


@pytest.fixture
def no_decoder(monkeypatch: pytest.MonkeyPatch) -> None:
    """Fail the test if pixels would be decoded."""

    def refuse(*_args: object, **_options: object) -> None:
        raise AssertionError("no decoder may be called")

    monkeypatch.setattr(image_decoding.cv2, "imdecode", refuse)
    monkeypatch.setattr(image_decoding.simplejpeg, "decode_jpeg", refuse)


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
        assert read_image_header(data[: sof_offset(data) + 19]).width == 40  # SOF0 with 3 components
        with pytest.raises(InvalidInput, match=r"truncated inside its frame header \(SOF0\)"):
            read_image_header(data[: sof_offset(data) + 18])
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
        with pytest.raises(InvalidInput, match="its IHDR chunk at byte 8 fails its CRC check"):
            decode_image(bytes(data), LIMIT)

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


class TestStrictJpeg:
    """libjpeg pads bad scan data with grey and only warns: every warning is an error here."""

    @pytest.mark.parametrize("seed", range(6))
    def test_garbage_scan_data_after_a_valid_header(self, seed: int) -> None:
        data = garbage_in_scan(sample_jpeg(), seed)
        assert read_image_header(data) == ImageHeader("jpeg", 640, 480, 3)
        assert opencv(data).shape == (480, 640, 3)  # what used to be scored and stored
        with pytest.raises(
            InvalidInput, match=r"JPEG image \(640x480\) cannot be decoded: .*corrupt"
        ) as info:
            decode_image(data, LIMIT)
        assert "re-encode the file" in info.value.detail

    def test_zeroed_scan_data(self) -> None:
        data = bytearray(sample_jpeg())
        start, end = scan_data(bytes(data))
        data[(start + end) // 2 : (start + end) // 2 + 64] = bytes(64)
        with pytest.raises(InvalidInput, match="libjpeg: Corrupt JPEG data"):
            decode_image(bytes(data), LIMIT)

    def test_bad_huffman_code(self) -> None:
        data = sample_jpeg()
        start, end = scan_data(data)
        with pytest.raises(InvalidInput, match="bad Huffman code"):
            decode_image(data[:start] + b"\xff\x00" * 2000 + data[end:], LIMIT)  # all-ones codes

    def test_extraneous_bytes_before_a_marker(self) -> None:
        data = sample_jpeg()
        sof = sof_offset(data)
        with pytest.raises(InvalidInput, match="2 extraneous bytes before marker 0xc0"):
            decode_image(data[:sof] + b"\x12\x34" + data[sof:], LIMIT)

    def test_a_marker_inside_the_scan_data(self) -> None:
        data = sample_jpeg()
        start, end = scan_data(data)
        middle = (start + end) // 2
        with pytest.raises(InvalidInput, match="marker 0xFFC0, invalid there"):
            decode_image(data[:middle] + b"\xff\xc0" + data[middle:], LIMIT)

    def test_header_larger_than_the_data(self) -> None:
        """Issue 13: a header saying 6000x6000 over 640x480 of data answered 200 with width 6000."""
        data = patch_jpeg_size(sample_jpeg(), 6000, 6000)
        assert opencv(data).shape == (6000, 6000, 3)
        with pytest.raises(
            InvalidInput, match=r"\(6000x6000\) cannot be decoded: .*shorter than its size says"
        ):
            decode_image(data, 40_000_000)

    def test_truncated_with_an_end_marker_appended(self) -> None:
        data = sample_jpeg()
        start, end = scan_data(data)
        cut = data[: (start + end) // 2] + b"\xff\xd9"
        assert opencv(cut).shape == (480, 640, 3)
        with pytest.raises(InvalidInput, match="premature end of data segment"):
            decode_image(cut, LIMIT)

    def test_progressive_cut_at_every_scan_boundary_with_an_end_marker(self) -> None:
        """libjpeg decodes these blurred and silently; the scan walk finds the missing coefficients."""
        data = encode(".jpg", opencv(sample_jpeg()), cv2.IMWRITE_JPEG_PROGRESSIVE, 1)
        boundaries = [i for i in range(len(data)) if data.startswith(b"\xff\xda", i)]
        assert len(boundaries) >= 6
        for boundary in boundaries[1:]:
            cut = data[:boundary] + b"\xff\xd9"
            assert opencv(cut).shape == (480, 640, 3)
            with pytest.raises(
                InvalidInput, match=r"component\(s\) [0-9, ]+ is incomplete at its end-of-image"
            ):
                decode_image(cut, LIMIT)
        np.testing.assert_array_equal(decode_image(data, LIMIT), opencv(data))

    def test_missing_end_marker(self) -> None:
        data = sample_jpeg()
        with pytest.raises(InvalidInput, match=r"truncated \(no end-of-image marker\)"):
            decode_image(data[: len(data) - 2], LIMIT)

    def test_bytes_after_the_end_marker_are_ignored(self) -> None:
        """Some cameras append data after EOI; the image itself is complete."""
        data = sample_jpeg()
        np.testing.assert_array_equal(decode_image(data + b"appended by a camera", LIMIT), opencv(data))

    def test_cmyk_jpeg_decodes_as_opencv_does(self) -> None:
        data = pil_jpeg(opencv(sample_jpeg()), "CMYK", quality=90)
        assert read_image_header(data).channels == 4
        decoded = decode_image(data, LIMIT)
        assert decoded.shape == (480, 640, 3)
        np.testing.assert_array_equal(decoded, opencv(data))


class TestStrictPng:
    def test_corrupted_idat_crc(self) -> None:
        data = with_bad_crc(encode(".png", colour(120, 160)), b"IDAT")
        with pytest.raises(
            InvalidInput, match=r"PNG image \(160x120\) cannot be decoded: its IDAT chunk .*CRC"
        ):
            decode_image(data, LIMIT)

    @pytest.mark.parametrize("kind", [b"IEND", b"tEXt"])
    def test_a_bad_crc_libpng_only_warns_about_is_refused(self, kind: bytes) -> None:
        chunks = png_chunks(encode(".png", colour()))
        data = build_png([chunks[0], (b"tEXt", b"Comment\x00hello"), *chunks[1:]])
        with pytest.raises(InvalidInput, match=f"its {kind.decode()} chunk .*CRC"):
            decode_image(with_bad_crc(data, kind), LIMIT)

    def test_truncated_mid_idat(self) -> None:
        data = encode(".png", colour(120, 160))
        with pytest.raises(InvalidInput, match="truncated inside its IDAT chunk"):
            decode_image(data[: len(data) // 2], LIMIT)
        with pytest.raises(InvalidInput, match="truncated inside its IDAT chunk"):
            decode_image(data[: len(data) // 2] + png_chunk(b"IEND", b""), LIMIT)

    def test_missing_end_chunk(self) -> None:
        data = encode(".png", colour())
        with pytest.raises(InvalidInput, match="ends before its IEND chunk"):
            decode_image(data[:-12], LIMIT)

    def test_pixel_data_shorter_than_the_header(self) -> None:
        """Well-formed chunks, but the IDAT stream holds only half the rows the header declares."""
        chunks = png_chunks(encode(".png", colour(120, 160)))
        rows = zlib.decompress(b"".join(payload for kind, payload in chunks if kind == b"IDAT"))
        data = build_png([chunks[0], (b"IDAT", zlib.compress(rows[: len(rows) // 2])), (b"IEND", b"")])
        with pytest.raises(InvalidInput, match="shorter than the header's size"):
            decode_image(data, LIMIT)

    def test_header_larger_than_the_data(self) -> None:
        data = patch_png_size(encode(".png", colour(480, 640)), 6000, 6000)
        with pytest.raises(
            InvalidInput, match=r"\(6000x6000\) cannot be decoded: .*shorter than the header's size"
        ):
            decode_image(data, 40_000_000)

    def test_no_pixel_data(self) -> None:
        chunks = png_chunks(encode(".png", colour()))
        with pytest.raises(InvalidInput, match="no pixel data"):
            decode_image(build_png([chunks[0], (b"IEND", b"")]), LIMIT)

    def test_bytes_after_the_end_chunk_are_ignored(self) -> None:
        image = colour()
        np.testing.assert_array_equal(decode_image(encode(".png", image) + b"trailer", LIMIT), image)

    @pytest.mark.parametrize(
        "image",
        [
            colour(),
            colour()[:, :, 0],
            colour().astype(np.uint16) * 257,
            colour()[:, :, 0].astype(np.uint16) * 257,
        ],
        ids=["rgb8", "gray8", "rgb16", "gray16"],
    )
    def test_valid_pngs_decode_exactly(self, image: np.ndarray) -> None:
        expected = (image // 257).astype(np.uint8) if image.dtype == np.uint16 else image
        np.testing.assert_array_equal(decode_image(encode(".png", image), LIMIT), expected)


def synthetic_jpegs() -> dict[str, bytes]:
    """JPEGs from two encoders over the subsamplings, qualities, progressive mode, gray and CMYK."""
    photo = opencv(sample_jpeg())
    odd = photo[3:478, 5:634]  # sizes that are no multiple of the MCU
    noise = np.random.default_rng(1).integers(0, 256, (97, 131, 3), dtype=np.uint8)
    samplings = {
        "411": cv2.IMWRITE_JPEG_SAMPLING_FACTOR_411,
        "420": cv2.IMWRITE_JPEG_SAMPLING_FACTOR_420,
        "422": cv2.IMWRITE_JPEG_SAMPLING_FACTOR_422,
        "440": cv2.IMWRITE_JPEG_SAMPLING_FACTOR_440,
        "444": cv2.IMWRITE_JPEG_SAMPLING_FACTOR_444,
    }
    files = {}
    for (name, image), (sampling, factor), quality, progressive in itertools.product(
        {"photo": photo, "odd": odd, "noise": noise}.items(), samplings.items(), (10, 95), (0, 1)
    ):
        files[f"opencv-{name}-{sampling}-q{quality}-p{progressive}"] = encode(
            ".jpg",
            image,
            cv2.IMWRITE_JPEG_SAMPLING_FACTOR,
            factor,
            cv2.IMWRITE_JPEG_QUALITY,
            quality,
            cv2.IMWRITE_JPEG_PROGRESSIVE,
            progressive,
        )
    for name, image in {"photo": photo, "odd": odd, "noise": noise}.items():
        gray = cv2.cvtColor(image, cv2.COLOR_BGR2GRAY)
        files[f"opencv-{name}-gray"] = encode(".jpg", gray, cv2.IMWRITE_JPEG_QUALITY, 90)
        files[f"opencv-{name}-restarts"] = encode(".jpg", image, cv2.IMWRITE_JPEG_RST_INTERVAL, 3)
        for subsampling, progressive in itertools.product((0, 1, 2), (False, True)):
            files[f"pillow-{name}-sub{subsampling}-p{progressive:d}"] = pil_jpeg(
                image, quality=85, subsampling=subsampling, progressive=progressive, optimize=True
            )
        files[f"pillow-{name}-gray"] = pil_jpeg(gray, "L", quality=70)
        files[f"pillow-{name}-cmyk"] = pil_jpeg(image, "CMYK", quality=90)
    return files


SYNTHETIC = synthetic_jpegs()


class TestIdenticalPixels:
    """The decoder changed (OpenCV -> simplejpeg); the pixels of valid files must not."""

    def test_samples_decode_as_opencv_decodes_them(self) -> None:
        assert len(SAMPLES) >= 12
        digest = hashlib.sha256()
        for path in SAMPLES:
            data = path.read_bytes()
            decoded = decode_image(data, LIMIT)
            np.testing.assert_array_equal(decoded, opencv(data), err_msg=path.name)
            digest.update(path.name.encode() + str(decoded.shape).encode() + decoded.tobytes())
        assert digest.hexdigest() == SAMPLES_DIGEST

    @pytest.mark.parametrize("name", sorted(SYNTHETIC))
    def test_synthetic_jpegs_decode_as_opencv_decodes_them(self, name: str) -> None:
        data = SYNTHETIC[name]
        decoded, expected = decode_image(data, LIMIT), opencv(data)
        assert decoded.dtype == expected.dtype == np.uint8
        np.testing.assert_array_equal(decoded, expected)
