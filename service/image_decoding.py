"""Untrusted image bytes -> pixels, refusing oversize images before any big allocation.

``read_image_header`` reads the dimensions straight from the PNG ``IHDR`` chunk or the
JPEG ``SOFn`` segment, walking the marker segments without touching the entropy-coded
data; ``decode_image`` checks them against the pixel limit and only then decodes.

Orientation: EXIF rotation is deliberately *not* applied (``IMREAD_UNCHANGED``), so the
decoded array has exactly the stored width and height and pixel coordinates mean what the
file's raw raster means (labels and boxes are given in that frame).
"""

from __future__ import annotations

import struct
import zlib
from collections.abc import Iterator
from dataclasses import dataclass
from typing import Literal

import cv2
import numpy as np

from service.errors import InvalidInput, PayloadTooLarge, UnsupportedMediaType

ACCEPTED_FORMATS = "JPEG or PNG"
PIXEL_LIMIT_SETTING = "CKS_MAX_IMAGE_PIXELS"

PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"
JPEG_SOI = b"\xff\xd8"

# PNG colour type -> channels as stored (palette images expand to 3).
_PNG_CHANNELS = {0: 1, 2: 3, 3: 3, 4: 2, 6: 4}
_PNG_BIT_DEPTHS = {0: (1, 2, 4, 8, 16), 2: (8, 16), 3: (1, 2, 4, 8), 4: (8, 16), 6: (8, 16)}

# JPEG markers. SOF0..SOF15 except DHT (C4), JPG (C8) and DAC (CC) carry the frame size.
_SOF_MARKERS = frozenset(range(0xC0, 0xD0)) - {0xC4, 0xC8, 0xCC}
_STANDALONE_MARKERS = frozenset({0x01, 0xD8, *range(0xD0, 0xD8)})  # TEM, SOI, RST0..RST7
_SOS, _EOI = 0xDA, 0xD9

_OTHER_SIGNATURES = (
    (b"GIF87a", "GIF"),
    (b"GIF89a", "GIF"),
    (b"BM", "BMP"),
    (b"II*\x00", "TIFF"),
    (b"MM\x00*", "TIFF"),
    (b"\x00\x00\x01\x00", "ICO"),
)


@dataclass(frozen=True)
class ImageHeader:
    """What the file says about itself, read without decoding any pixel."""

    format: Literal["jpeg", "png"]
    width: int
    height: int
    channels: int

    @property
    def pixels(self) -> int:
        return self.width * self.height


def read_image_header(data: bytes) -> ImageHeader:
    """Parse format, size and channel count from the first bytes of a JPEG or PNG.

    Raises ``InvalidInput`` for empty, truncated or malformed headers and
    ``UnsupportedMediaType`` for anything that is neither JPEG nor PNG.
    """
    if not data:
        raise InvalidInput(f"the image is empty (0 bytes); send a {ACCEPTED_FORMATS} file")
    if data.startswith(PNG_SIGNATURE):
        return _png_header(data)
    if data.startswith(JPEG_SOI):
        return _jpeg_header(data)
    raise UnsupportedMediaType(
        f"the image is {_guess_format(data)}; only {ACCEPTED_FORMATS} images are accepted"
    )


def decode_image(data: bytes, max_pixels: int) -> np.ndarray:
    """Decode a JPEG or PNG into uint8 pixels: BGR ``(H, W, 3)`` or gray ``(H, W)``.

    The header is checked first: ``PayloadTooLarge`` when ``width * height`` exceeds
    ``max_pixels`` (setting ``CKS_MAX_IMAGE_PIXELS``), before anything is decoded.
    16-bit samples are scaled to 8 bits and alpha is dropped. A good header followed
    by corrupt or truncated data gives ``InvalidInput``.
    """
    header = read_image_header(data)
    _check_pixel_limit(header, max_pixels)
    if header.format == "jpeg":
        _require_complete_jpeg(data, header)
    try:
        image = cv2.imdecode(np.frombuffer(data, dtype=np.uint8), cv2.IMREAD_UNCHANGED)
    except cv2.error as exc:
        raise _corrupt(header, "the decoder failed") from exc
    if image is None:
        raise _corrupt(header, "the pixel data is corrupt or truncated")
    if image.shape[:2] != (header.height, header.width):
        raise _corrupt(header, f"the decoded size {image.shape[1]}x{image.shape[0]} contradicts the header")
    return _to_bgr_or_gray_uint8(image, header)


def _check_pixel_limit(header: ImageHeader, max_pixels: int) -> None:
    if header.pixels > max_pixels:
        raise PayloadTooLarge(
            f"the {header.format.upper()} image is {header.width}x{header.height} = {header.pixels} pixels, "
            f"above the limit of {max_pixels} pixels ({PIXEL_LIMIT_SETTING}); send a smaller image"
        )


def _corrupt(header: ImageHeader, why: str) -> InvalidInput:
    return InvalidInput(
        f"the {header.format.upper()} image ({header.width}x{header.height}) cannot be decoded: {why}; "
        "re-encode the file and send it again"
    )


def _to_bgr_or_gray_uint8(image: np.ndarray, header: ImageHeader) -> np.ndarray:
    if image.dtype == np.uint16:
        image = ((image.astype(np.uint32) + 128) // 257).astype(np.uint8)
    elif image.dtype != np.uint8:
        raise _corrupt(header, f"unsupported sample type {image.dtype}")
    if image.ndim == 2:
        return image
    channels = image.shape[2]
    if channels in (1, 2) or header.channels in (1, 2):  # gray (+ alpha), maybe expanded to B = G = R
        return np.ascontiguousarray(image[:, :, 0])
    if channels == 4:
        return cv2.cvtColor(image, cv2.COLOR_BGRA2BGR)
    if channels == 3:
        return image
    raise _corrupt(header, f"unsupported channel count {channels}")


def _guess_format(data: bytes) -> str:
    for signature, name in _OTHER_SIGNATURES:
        if data.startswith(signature):
            return f"a {name} file"
    if data[:4] == b"RIFF" and data[8:12] == b"WEBP":
        return "a WebP file"
    return "not a recognised image format"


# ---------------------------------------------------------------- PNG


def _png_header(data: bytes) -> ImageHeader:
    """The IHDR chunk must come first: length 13, then width, height, depth, colour type."""
    chunk = data[8 : 8 + 8 + 13 + 4]
    if len(chunk) < 25:
        raise InvalidInput("the PNG image is truncated: its IHDR header chunk is incomplete")
    length, kind = struct.unpack(">I4s", chunk[:8])
    if kind != b"IHDR" or length != 13:
        raise InvalidInput("the PNG image is malformed: it does not start with a 13-byte IHDR chunk")
    (crc,) = struct.unpack(">I", chunk[21:25])
    if zlib.crc32(chunk[4:21]) != crc:
        raise InvalidInput("the PNG image is corrupt: the IHDR chunk fails its CRC check")
    width, height, depth, colour = struct.unpack(">IIBB", chunk[8:18])
    if width == 0 or height == 0 or width > 2**31 - 1 or height > 2**31 - 1:
        raise InvalidInput(f"the PNG image declares an invalid size {width}x{height}")
    if colour not in _PNG_CHANNELS or depth not in _PNG_BIT_DEPTHS[colour]:
        raise InvalidInput(f"the PNG image declares an invalid colour type {colour} / bit depth {depth}")
    return ImageHeader("png", width, height, _PNG_CHANNELS[colour])


# ---------------------------------------------------------------- JPEG


def _jpeg_segments(data: bytes) -> Iterator[tuple[int, int, int]]:
    """Yield ``(marker, payload start, payload length)`` for each segment after SOI.

    Mirrors libjpeg's ``next_marker``: bytes that are not 0xFF before a marker are
    skipped, any number of 0xFF fill bytes may precede the marker code, and standalone
    markers (RSTn, TEM) have no length. Stops after yielding SOS (entropy data follows).
    """
    pos, end = 2, len(data)
    while True:
        while pos < end and data[pos] != 0xFF:
            pos += 1
        while pos < end and data[pos] == 0xFF:
            pos += 1
        if pos >= end:
            raise InvalidInput("the JPEG image is truncated in its headers (no frame header or scan found)")
        marker = data[pos]
        pos += 1
        if marker == 0x00 or marker in _STANDALONE_MARKERS:
            continue
        if marker == _EOI:
            raise InvalidInput("the JPEG image ends (EOI) before its scan data")
        if pos + 2 > end:
            raise InvalidInput("the JPEG image is truncated inside a segment length")
        (length,) = struct.unpack(">H", data[pos : pos + 2])
        if length < 2:
            raise InvalidInput(f"the JPEG image is malformed: segment 0xFF{marker:02X} has length {length}")
        yield marker, pos + 2, length - 2
        if marker == _SOS:
            return
        pos += length


def _jpeg_header(data: bytes) -> ImageHeader:
    """Return the header from the first SOFn segment (as libjpeg does)."""
    for marker, start, size in _jpeg_segments(data):
        if marker in _SOF_MARKERS:
            return _parse_sof(data, marker, start, size)
        if marker == _SOS:
            raise InvalidInput("the JPEG image is malformed: scan data (SOS) before the frame header")
    raise AssertionError("unreachable: _jpeg_segments ends with SOS or raises")


def _parse_sof(data: bytes, marker: int, start: int, size: int) -> ImageHeader:
    if size < 6 or start + 6 > len(data):
        raise InvalidInput(f"the JPEG image is truncated inside its frame header (SOF{marker - 0xC0})")
    _precision, height, width, components = struct.unpack(">BHHB", data[start : start + 6])
    if height == 0 or width == 0:
        raise InvalidInput(
            f"the JPEG image declares an unsupported size {width}x{height} "
            "(height defined later by a DNL marker is not supported)"
        )
    if components not in (1, 3, 4):
        raise InvalidInput(f"the JPEG image has {components} colour components; 1, 3 or 4 are supported")
    return ImageHeader("jpeg", width, height, components)


def _require_complete_jpeg(data: bytes, header: ImageHeader) -> None:
    """A complete JPEG has a scan and, after it, an EOI marker (0xFF in scan data is stuffed).

    libjpeg pads a truncated file with gray and only warns, so this is checked here.
    """
    try:
        scan_start = next(start + size for marker, start, size in _jpeg_segments(data) if marker == _SOS)
    except InvalidInput as exc:
        raise _corrupt(header, "the file is truncated before its scan data") from exc
    if data.find(b"\xff\xd9", scan_start) < 0:
        raise _corrupt(header, "the file is truncated (no end-of-image marker)")
