"""Untrusted image bytes -> pixels, refusing oversize images before any big allocation.

``read_image_header`` reads the dimensions straight from the PNG ``IHDR`` chunk or the
JPEG ``SOFn`` segment, walking the marker segments without touching the entropy-coded
data; ``decode_image`` checks them against the pixel limit, then the memory the decode
would take against the byte limit, and only then decodes.

Memory: decoding goes straight to 8-bit BGR or gray wherever that gives the same pixels:
JPEG always (libjpeg converts while decoding), PNG at 8 bits (libpng drops alpha and
expands palettes and low bit depths row by row). A 16-bit PNG is decoded at 16 bits (its
3 or 1 channels only) and scaled to 8 with ``(v + 128) // 257`` a block of rows at a time,
because libpng's own reduction rounds differently and the bundled calibration was scored
with this rounding. So a decode takes at most (``decoded_bytes``): for a JPEG its 8-bit
result, plus libjpeg's buffer of every DCT coefficient (2 bytes per sample) for a
progressive or multi-scan file, plus 4 bytes a pixel for CMYK; for a PNG twice its
decoded array (OpenCV's ``imdecode`` decodes into one and returns a copy), which is the
8-bit result or, at 16 bits, twice that.

Decoding is strict, the same for predict and calibration: a truncated or corrupt file is
``InvalidInput``, never a partly grey image. JPEG: libjpeg-turbo through ``simplejpeg``
with ``strict=True``, so every libjpeg warning (corrupt data, premature end of a data
segment or of the file, unknown markers, extraneous bytes) is an error; and every
component's every DCT coefficient must arrive in some scan before the EOI marker (libjpeg
decodes a progressive file cut between scans, with an EOI appended, blurred and silently).
Its pixels are bit-identical to OpenCV's ``imdecode(IMREAD_UNCHANGED)``, the decoder the
bundled calibration was scored with (checked by tests/inputs/test_image_decoding.py), and
it decodes a 640x480 JPEG faster. PNG: OpenCV (libpng), after every chunk up to ``IEND``
has been found complete and matching its CRC (libpng only warns about a bad CRC in IEND
or an ancillary chunk); IDAT data shorter than the header's size is libpng's error, more
data than it needs only a warning and accepted. Bytes after the end marker (EOI, IEND)
are ignored, as the decoders do: some cameras append data there.

Orientation: EXIF rotation is deliberately *not* applied, so the decoded array has exactly
the stored width and height and pixel coordinates mean what the file's raw raster means
(labels and boxes are given in that frame).
"""

from __future__ import annotations

import re
import struct
import zlib
from collections.abc import Iterator
from dataclasses import dataclass
from typing import Literal

import cv2
import numpy as np
import simplejpeg

from service.errors import InvalidInput, PayloadTooLarge, UnsupportedMediaType

ACCEPTED_FORMATS = "JPEG or PNG"
PIXEL_LIMIT_SETTING = "CKS_MAX_IMAGE_PIXELS"
BYTES_LIMIT_SETTING = "CKS_MAX_DECODED_BYTES"
_SCALING_BLOCK_SAMPLES = 1 << 18  # 16-bit samples scaled to 8 bits at a time (1 MiB in 32-bit)

PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"
_PNG_DEPTH_OFFSET = 24  # the IHDR's bit depth: signature, chunk length and type, width, height
JPEG_SOI = b"\xff\xd8"

# PNG colour type -> channels as stored (palette images expand to 3).
_PNG_CHANNELS = {0: 1, 2: 3, 3: 3, 4: 2, 6: 4}
_PNG_BIT_DEPTHS = {0: (1, 2, 4, 8, 16), 2: (8, 16), 3: (1, 2, 4, 8), 4: (8, 16), 6: (8, 16)}

# JPEG markers. SOF0..SOF15 except DHT (C4), JPG (C8) and DAC (CC) carry the frame size.
_SOF_MARKERS = frozenset(range(0xC0, 0xD0)) - {0xC4, 0xC8, 0xCC}
_STANDALONE_MARKERS = frozenset({0x01, 0xD8, *range(0xD0, 0xD8)})  # TEM, SOI, RST0..RST7
_PROGRESSIVE_SOF_MARKERS = frozenset({0xC2, 0xC6, 0xCA, 0xCE})
_SOS, _EOI = 0xDA, 0xD9
# In entropy-coded data a marker is 0xFF followed by anything but 0x00 (a stuffed 0xFF
# byte), RST0..RST7 (inside the scan) or 0xFF (fill byte before the marker).
_MARKER_AFTER_SCAN = re.compile(rb"\xff[^\x00\xd0-\xd7\xff]")
# What may follow a scan: tables (DHT, DAC, DQT, DRI), DNL, the next scan, comments, APPn, EOI.
_BETWEEN_SCANS = frozenset({0xC4, 0xCC, 0xDB, 0xDD, 0xDC, _SOS, 0xFE, *range(0xE0, 0xF0), _EOI})

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


def decode_image(data: bytes, max_pixels: int, max_bytes: int | None = None) -> np.ndarray:
    """Decode a JPEG or PNG into uint8 pixels: BGR ``(H, W, 3)`` or gray ``(H, W)``.

    The header is checked first: ``PayloadTooLarge`` when ``width * height`` exceeds
    ``max_pixels`` (setting ``CKS_MAX_IMAGE_PIXELS``) or the decode would take more than
    ``max_bytes`` of memory (``CKS_MAX_DECODED_BYTES``; None: no such limit), before
    anything is decoded. 16-bit samples are scaled to 8 bits and alpha is dropped. A good
    header followed by corrupt, truncated or too little data gives ``InvalidInput``.
    """
    header = read_image_header(data)
    _check_pixel_limit(header, max_pixels)
    needed = decoded_bytes(data, header)
    if max_bytes is not None and needed > max_bytes:
        raise PayloadTooLarge(
            f"decoding the {header.format.upper()} image ({header.width}x{header.height}) would take {needed}"
            f" bytes of memory, above the limit of {max_bytes} bytes ({BYTES_LIMIT_SETTING}); send a smaller"
            " image (16-bit samples and progressive JPEGs take more memory per pixel)"
        )
    image = _decode_jpeg(data, header) if header.format == "jpeg" else _decode_png(data, header)
    if image.shape[:2] != (header.height, header.width) or image.ndim != (2 if _gray(header) else 3):
        raise _corrupt(header, f"the decoded shape {image.shape} contradicts the header")
    return _to_uint8(image, header)


def decoded_bytes(data: bytes, header: ImageHeader) -> int:
    """The memory ``decode_image`` allocates for this image at its peak, from its headers alone.

    Raises ``InvalidInput`` when the JPEG's segments are corrupt or incomplete.
    """
    result = header.pixels * (1 if _gray(header) else 3)
    if header.format == "png":
        return result * (4 if data[_PNG_DEPTH_OFFSET] == 16 else 2)  # OpenCV copies its decoded array
    cmyk = header.pixels * 4 if header.channels == 4 else 0
    return result + cmyk + _require_complete_jpeg(data, header)


def _gray(header: ImageHeader) -> bool:
    return header.channels in (1, 2)


def _decode_jpeg(data: bytes, header: ImageHeader) -> np.ndarray:
    colorspace = "GRAY" if header.channels == 1 else "BGR"
    try:
        image = simplejpeg.decode_jpeg(data, colorspace=colorspace, strict=True)
    except ValueError as exc:
        why = f"the file is corrupt or shorter than its size says (libjpeg: {exc})"
        raise _corrupt(header, why) from exc
    return image[:, :, 0] if header.channels == 1 else image


def _decode_png(data: bytes, header: ImageHeader) -> np.ndarray:
    _require_intact_png(data, header)
    flags = cv2.IMREAD_IGNORE_ORIENTATION | (cv2.IMREAD_GRAYSCALE if _gray(header) else cv2.IMREAD_COLOR)
    if data[_PNG_DEPTH_OFFSET] == 16:
        flags |= cv2.IMREAD_ANYDEPTH
    try:
        image = cv2.imdecode(np.frombuffer(data, dtype=np.uint8), flags)
    except cv2.error as exc:
        raise _corrupt(header, "the decoder failed") from exc
    if image is None:
        raise _corrupt(header, "its compressed pixel data is corrupt or shorter than the header's size")
    return image


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


def _to_uint8(image: np.ndarray, header: ImageHeader) -> np.ndarray:
    if image.dtype == np.uint8:
        return image
    if image.dtype != np.uint16:
        raise _corrupt(header, f"unsupported sample type {image.dtype}")
    result = np.empty(image.shape, np.uint8)
    rows = max(1, _SCALING_BLOCK_SAMPLES // image[0].size)
    for start in range(0, image.shape[0], rows):
        block = image[start : start + rows].astype(np.uint32)
        block += 128
        block //= 257
        result[start : start + rows] = block
    return result


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


def _require_intact_png(data: bytes, header: ImageHeader) -> None:
    """Every chunk up to IEND complete and matching its CRC, and at least one IDAT chunk."""
    view, pos, end, has_pixels = memoryview(data), 8, len(data), False
    while True:
        if pos + 12 > end:
            raise _corrupt(header, "the file is truncated (it ends before its IEND chunk)")
        length, kind = struct.unpack_from(">I4s", data, pos)
        name = kind.decode("ascii", "replace")
        if pos + 12 + length > end:
            raise _corrupt(header, f"the file is truncated inside its {name} chunk")
        (crc,) = struct.unpack_from(">I", data, pos + 8 + length)
        if zlib.crc32(view[pos + 4 : pos + 8 + length]) != crc:
            raise _corrupt(header, f"its {name} chunk at byte {pos} fails its CRC check (it is corrupt)")
        has_pixels = has_pixels or kind == b"IDAT"
        if kind == b"IEND":
            break
        pos += 12 + length
    if not has_pixels:
        raise _corrupt(header, "it has no pixel data (IDAT chunk)")


# ---------------------------------------------------------------- JPEG


class _Malformed(Exception):
    """A structural fault, worded to follow "the JPEG image"."""


def _jpeg_segments(data: bytes, through_scans: bool = False) -> Iterator[tuple[int, int, int]]:
    """Yield ``(marker, payload start, payload length)`` for each segment after SOI.

    Mirrors libjpeg's ``next_marker``: bytes that are not 0xFF before a marker are
    skipped, any number of 0xFF fill bytes may precede the marker code, and standalone
    markers (RSTn, TEM) have no length. Stops after yielding SOS (entropy data follows),
    or, ``through_scans``, skips each scan's entropy-coded data and stops after yielding
    EOI (payload length 0). Raises ``_Malformed``.
    """
    pos, end = 2, len(data)
    while True:
        while pos < end and data[pos] != 0xFF:
            pos += 1
        while pos < end and data[pos] == 0xFF:
            pos += 1
        if pos >= end:
            if through_scans:
                raise _Malformed("is truncated (no end-of-image marker)")
            raise _Malformed("is truncated in its headers (no frame header or scan found)")
        marker = data[pos]
        pos += 1
        if marker == 0x00 or marker in _STANDALONE_MARKERS:
            continue
        if marker == _EOI:
            if not through_scans:
                raise _Malformed("ends (EOI) before its scan data")
            yield marker, pos, 0
            return
        if pos + 2 > end:
            raise _Malformed("is truncated inside a segment length")
        (length,) = struct.unpack(">H", data[pos : pos + 2])
        if length < 2:
            raise _Malformed(f"is malformed: segment 0xFF{marker:02X} has length {length}")
        yield marker, pos + 2, length - 2
        pos += length
        if marker == _SOS:
            if not through_scans:
                return
            found = _MARKER_AFTER_SCAN.search(data, pos)
            if found is None:
                raise _Malformed("is truncated (no end-of-image marker)")
            if data[found.start() + 1] not in _BETWEEN_SCANS:
                raise _Malformed(
                    f"is corrupt: its compressed data holds marker 0xFF{data[found.start() + 1]:02X}, "
                    "invalid there"
                )
            pos = found.start()


def _jpeg_header(data: bytes) -> ImageHeader:
    """Return the header from the first SOFn segment (as libjpeg does)."""
    try:
        for marker, start, size in _jpeg_segments(data):
            if marker in _SOF_MARKERS:
                return _parse_sof(data, marker, start, size)
            if marker == _SOS:
                raise InvalidInput("the JPEG image is malformed: scan data (SOS) before the frame header")
    except _Malformed as exc:
        raise InvalidInput(f"the JPEG image {exc}") from None
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


def _require_complete_jpeg(data: bytes, header: ImageHeader) -> int:
    """Check that every frame component's every DCT coefficient arrives, to full precision,
    before EOI; return the bytes of libjpeg's buffer of every coefficient, which it fills
    for a progressive or multi-scan file (0 for a file decoded in one pass).

    libjpeg leaves missing coefficients at zero without a warning when a file cut at a
    scan boundary ends with EOI: a sequential file then lacks a component, a progressive
    one its detail (a scan with successive-approximation bit Al > 0 needs a refinement
    down to Al = 0). Lossless frames (SOF3, ...) need each component in some scan.
    """
    components: list[int] = []
    sampling = b""
    progressive = False
    first_scan_components = 0
    missing: set[tuple[int, int]] = set()
    try:
        for marker, start, size in _jpeg_segments(data, through_scans=True):
            payload = data[start : start + size]
            if marker in _SOF_MARKERS and not components:
                components = list(payload[6 : 6 + 3 * header.channels : 3])
                sampling = payload[7 : 7 + 3 * header.channels : 3]
                progressive = marker in _PROGRESSIVE_SOF_MARKERS
                missing = {(c, k) for c in components for k in range(64 if progressive else 1)}
            elif marker == _SOS:
                missing -= _scan_coverage(payload, progressive)
                first_scan_components = first_scan_components or payload[0]
    except _Malformed as exc:
        raise _corrupt(header, f"it {exc}") from None
    if len(components) != header.channels or len(sampling) != header.channels:
        raise _corrupt(header, "it is truncated inside its frame header")
    if missing:
        lacking = ", ".join(str(c) for c in sorted({c for c, _ in missing}))
        raise _corrupt(
            header,
            f"it is truncated: the data of component(s) {lacking} is incomplete at its end-of-image marker",
        )
    if not progressive and first_scan_components == len(components):
        return 0
    return _coefficient_bytes(header, [(h >> 4, h & 0x0F) for h in sampling])


def _coefficient_bytes(header: ImageHeader, sampling: list[tuple[int, int]]) -> int:
    """libjpeg's whole-image coefficient buffer: 64 2-byte coefficients per 8x8 block of each
    component, padded to whole MCUs."""
    h_max = max(max(h for h, _ in sampling), 1)
    v_max = max(max(v for _, v in sampling), 1)
    mcu_columns = -(-header.width // (8 * h_max))
    mcu_rows = -(-header.height // (8 * v_max))
    return 128 * sum(mcu_columns * h * mcu_rows * v for h, v in sampling)


def _scan_coverage(payload: bytes, progressive: bool) -> set[tuple[int, int]]:
    """(component id, coefficient index) pairs a scan delivers to full precision."""
    count = payload[0] if payload else 0
    if count == 0 or len(payload) < 1 + 2 * count + 3:
        raise _Malformed("has a truncated scan header (SOS)")
    components = payload[1 : 1 + 2 * count : 2]
    first, last, approximation = payload[1 + 2 * count : 4 + 2 * count]
    if not progressive:
        return {(c, 0) for c in components}
    if approximation & 0x0F:
        return set()
    return {(c, k) for c in components for k in range(first, min(last, 63) + 1)}
