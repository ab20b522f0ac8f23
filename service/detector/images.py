"""Untrusted image bytes -> checked size -> decoded uint8 BGR or gray pixels, or a clear refusal.

The size comes from the PNG ``IHDR`` chunk or the JPEG frame header; an image above the pixel
limit, or whose decode would take more memory than the byte limit (``decoded_bytes``), is
refused before anything is decoded. Decoding is strict: a truncated or corrupt file is
``InvalidInput``, never a partly grey image; bytes after the end marker (EOI, IEND) are
ignored, as the decoders do (some cameras append data there). EXIF orientation is not
applied: pixel coordinates mean what the file's raw raster means.

JPEG: libjpeg-turbo through ``simplejpeg``, ``strict=True`` (every libjpeg warning is an
error), bit-identical to OpenCV's ``imdecode(IMREAD_UNCHANGED)``, which the bundled
calibration was scored with. ``decode_jpeg_window`` decodes only a window of it (the system's
libjpeg-turbo, through the C extension ``_jpeg_window``: rows above and below it entropy-decoded
only, columns beside it not at all), to the same pixels there and with the same strictness:
corrupt data anywhere is still refused. libjpeg decodes a file cut between scans with an EOI appended
silently, so the segments are walked first: every DCT coefficient of every component must
arrive before EOI. PNG: every chunk up to ``IEND`` complete with a matching CRC (libpng only
warns about some), then OpenCV (libpng) straight to 8 bits, alpha dropped; 16-bit samples
are scaled as ``(v + 128) // 257``, the calibration's rounding.
"""

from __future__ import annotations

import re
import struct
import zlib
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from typing import Literal

import cv2
import numpy as np
import simplejpeg

from service.errors import InvalidInput, PayloadTooLarge, UnsupportedMediaType

_JPEG_WINDOW_VERSION = 1  # service/detector/native/jpeg_window.c's VERSION
try:  # built from service/detector/native/jpeg_window.c where libjpeg's headers were found
    from service.detector import _jpeg_window
except ImportError:  # pragma: no cover - then JPEGs are decoded whole, to the same pixels
    _jpeg_window = None
_decode_window = (
    _jpeg_window.decode_window
    if _jpeg_window is not None and getattr(_jpeg_window, "VERSION", None) == _JPEG_WINDOW_VERSION
    else None  # a build of older sources
)

ACCEPTED_FORMATS = "JPEG or PNG"
PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"
_PNG_DEPTH_OFFSET = 24  # the IHDR's bit depth: signature, chunk length and type, width, height
_PNG_CHANNELS = {0: 1, 2: 3, 3: 3, 4: 2, 6: 4}  # colour type -> channels (a palette expands to 3)
_PNG_BIT_DEPTHS = {0: (1, 2, 4, 8, 16), 2: (8, 16), 3: (1, 2, 4, 8), 4: (8, 16), 6: (8, 16)}
_SCALING_BLOCK_SAMPLES = 1 << 18  # 16-bit samples scaled to 8 bits at a time (1 MiB in 32-bit)

# A marker as libjpeg's next_marker finds it, after any bytes and 0xFF fill bytes: 0xFF and a
# code that is not 0x00 (a stuffed 0xFF in scan data) nor RST0..RST7 (standalone, in scan data).
_JPEG_MARKER = re.compile(rb"\xff[^\x00\xd0-\xd7\xff]")  # no group, no "\xff+": both make it 2-10x slower
_SOF_MARKERS = frozenset(range(0xC0, 0xD0)) - {0xC4, 0xC8, 0xCC}  # not DHT, JPG, DAC
_PROGRESSIVE_SOF_MARKERS = frozenset({0xC2, 0xC6, 0xCA, 0xCE})
_SOS, _EOI = 0xDA, 0xD9
# What may follow a scan: tables (DHT, DAC, DQT, DRI), DNL, the next scan, comments, APPn, EOI.
_BETWEEN_SCANS = frozenset({0xC4, 0xCC, 0xDB, 0xDD, 0xDC, _SOS, 0xFE, *range(0xE0, 0xF0), _EOI})

_OTHER_FORMATS = {b"GIF87a": "GIF", b"GIF89a": "GIF", b"BM": "BMP", b"II*\x00": "TIFF", b"MM\x00*": "TIFF"}


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
    """Format, size and channels of a JPEG or PNG from its first bytes: ``InvalidInput`` for
    an empty, truncated or malformed header, ``UnsupportedMediaType`` for any other format."""
    if not data:
        raise InvalidInput(f"the image is empty (0 bytes); send a {ACCEPTED_FORMATS} file")
    if data.startswith(PNG_SIGNATURE):
        return _png_header(data)
    if data.startswith(b"\xff\xd8"):
        return _jpeg_header(data)
    raise UnsupportedMediaType(
        f"the image is {_guess_format(data)}; only {ACCEPTED_FORMATS} images are accepted"
    )


def decode_image(data: bytes, max_pixels: int, max_bytes: int | None = None) -> np.ndarray:
    """Decode a JPEG or PNG into uint8 pixels: BGR ``(H, W, 3)`` or gray ``(H, W)``.

    ``PayloadTooLarge``, before anything is decoded, when ``width * height`` exceeds
    ``max_pixels`` (``CKS_MAX_IMAGE_PIXELS``) or the decode would take more than ``max_bytes``
    of memory (None: no such limit). ``InvalidInput`` for a good
    header followed by corrupt, truncated or too little data.
    """
    return decode_checked(data, checked_image_header(data, max_pixels, max_bytes))


def checked_image_header(data: bytes, max_pixels: int, max_bytes: int | None = None) -> ImageHeader:
    """The header of an image that may be decoded: ``decode_image``'s refusals, before decoding."""
    header = read_image_header(data)
    name, size = header.format.upper(), f"{header.width}x{header.height}"
    if header.pixels > max_pixels:
        raise PayloadTooLarge(
            f"the {name} image is {size} = {header.pixels} pixels, above the limit of {max_pixels}"
            " pixels (CKS_MAX_IMAGE_PIXELS); send a smaller image"
        )
    needed = decoded_bytes(data, header)
    if max_bytes is not None and needed > max_bytes:
        raise PayloadTooLarge(
            f"decoding the {name} image ({size}) would take {needed} bytes of memory, above the limit"
            f" of {max_bytes} bytes per image; send a smaller image (16-bit samples and"
            " progressive JPEGs take more memory per pixel)"
        )
    return header


def decode_checked(data: bytes, header: ImageHeader) -> np.ndarray:
    """The whole image whose ``header`` ``checked_image_header`` gave."""
    return _decode_jpeg(data, header) if header.format == "jpeg" else _decode_png(data, header)


def jpeg_windows_available() -> bool:
    """Whether ``decode_jpeg_window`` can decode windows (its C extension built from these sources)."""
    return _decode_window is not None


def decode_jpeg_window(data: bytes, header: ImageHeader, window: tuple[int, int, int, int]) -> Window | None:
    """The pixels of a JPEG (``header`` checked) that cover ``window`` (``x0, y0, x1, y1``,
    half-open, inside the image), and where they lie: the full decode's pixels there. None where
    this cannot be done: a CMYK JPEG, or the extension not built."""
    if _decode_window is None or header.format != "jpeg" or header.channels not in (1, 3):
        return None
    gray = header.channels == 1
    try:
        pixels, x, y, width, height = _decode_window(data, *window, gray)
    except ValueError as exc:
        raise _corrupt(header, f"the file is corrupt or shorter than its size says (libjpeg: {exc})") from exc
    shape = (height, width) if gray else (height, width, 3)
    return Window(x, y, np.frombuffer(pixels, np.uint8).reshape(shape))


@dataclass(frozen=True)
class Window:
    """Decoded pixels of a rectangle of an image at ``(x, y)``: BGR ``(h, w, 3)`` or gray ``(h, w)``."""

    x: int
    y: int
    pixels: np.ndarray


def decoded_bytes(data: bytes, header: ImageHeader) -> int:
    """The memory ``decode_image`` allocates for this image at its peak, from its headers alone.

    Raises ``InvalidInput`` when a JPEG's segments are corrupt or incomplete.
    """
    result = header.pixels * (1 if header.channels in (1, 2) else 3)
    if header.format == "png":
        return result * (4 if data[_PNG_DEPTH_OFFSET] == 16 else 2)
    cmyk = header.pixels * 4 if header.channels == 4 else 0
    return result + cmyk + _complete_jpeg_coefficient_bytes(data, header)


def _corrupt(header: ImageHeader, why: str) -> InvalidInput:
    return InvalidInput(
        f"the {header.format.upper()} image ({header.width}x{header.height}) cannot be decoded: {why}; "
        "re-encode the file and send it again"
    )


def _guess_format(data: bytes) -> str:
    if data[:4] == b"RIFF" and data[8:12] == b"WEBP":
        return "a WebP file"
    for signature, name in _OTHER_FORMATS.items():
        if data.startswith(signature):
            return f"a {name} file"
    return "not a recognised image format"


# ---------------------------------------------------------------- PNG


def _png_header(data: bytes) -> ImageHeader:
    if len(data) < 33:  # signature, then the 13-byte IHDR chunk with its length, type and CRC
        raise InvalidInput("the PNG image is truncated: its IHDR header chunk is incomplete")
    length, kind, width, height, depth, colour = struct.unpack_from(">I4sIIBB", data, 8)
    if kind != b"IHDR" or length != 13:
        raise InvalidInput("the PNG image is malformed: it does not start with a 13-byte IHDR chunk")
    if not (0 < width < 2**31 and 0 < height < 2**31):
        raise InvalidInput(f"the PNG image declares an invalid size {width}x{height}")
    if depth not in _PNG_BIT_DEPTHS.get(colour, ()):
        raise InvalidInput(f"the PNG image declares an invalid colour type {colour} / bit depth {depth}")
    return ImageHeader("png", width, height, _PNG_CHANNELS[colour])


def _decode_png(data: bytes, header: ImageHeader) -> np.ndarray:
    _require_intact_png(data, header)
    sixteen_bit = data[_PNG_DEPTH_OFFSET] == 16
    colour = cv2.IMREAD_GRAYSCALE if header.channels in (1, 2) else cv2.IMREAD_COLOR
    flags = cv2.IMREAD_IGNORE_ORIENTATION | colour | (cv2.IMREAD_ANYDEPTH if sixteen_bit else 0)
    try:
        image = cv2.imdecode(np.frombuffer(data, np.uint8), flags)
    except cv2.error as exc:
        raise _corrupt(header, "the decoder failed") from exc
    if image is None:
        raise _corrupt(header, "its compressed pixel data is corrupt or shorter than the header's size")
    return _to_uint8(image) if sixteen_bit else image


def _require_intact_png(data: bytes, header: ImageHeader) -> None:
    """Every chunk up to IEND complete and matching its CRC, and at least one IDAT chunk."""
    pos, has_pixels = 8, False
    while True:
        if pos + 12 > len(data):
            raise _corrupt(header, "the file is truncated (it ends before its IEND chunk)")
        length, kind = struct.unpack_from(">I4s", data, pos)
        name, crc_at = kind.decode("ascii", "replace"), pos + 8 + length
        if crc_at + 4 > len(data):
            raise _corrupt(header, f"the file is truncated inside its {name} chunk")
        if zlib.crc32(memoryview(data)[pos + 4 : crc_at]) != int.from_bytes(data[crc_at : crc_at + 4]):
            raise _corrupt(header, f"its {name} chunk at byte {pos} fails its CRC check (it is corrupt)")
        has_pixels = has_pixels or kind == b"IDAT"
        if kind == b"IEND":
            break
        pos = crc_at + 4
    if not has_pixels:
        raise _corrupt(header, "it has no pixel data (IDAT chunk)")


def _to_uint8(image: np.ndarray) -> np.ndarray:
    """16-bit samples to 8 as ``(v + 128) // 257``, a block of rows at a time to bound memory."""
    result = np.empty(image.shape, np.uint8)
    rows = max(1, _SCALING_BLOCK_SAMPLES // image[0].size)
    for start in range(0, image.shape[0], rows):
        block = image[start : start + rows].astype(np.uint32)
        block += 128
        block //= 257
        result[start : start + rows] = block
    return result


# ---------------------------------------------------------------- JPEG


def _jpeg_segments(data: bytes, refuse: Callable[[str], InvalidInput]) -> Iterator[tuple[int, bytes]]:
    """Yield ``(marker, payload)`` for each segment after SOI, up to EOI, skipping each scan's
    entropy-coded data the way libjpeg does; a fault is ``refuse(why)``, worded to follow "it"."""
    pos, scanned = 2, False
    while True:
        found = _JPEG_MARKER.search(data, pos)
        if found is None:
            raise refuse(
                "is truncated (no end-of-image marker)" if scanned else "is truncated in its headers"
            )
        pos = found.end()
        marker = data[pos - 1]
        if scanned and marker not in _BETWEEN_SCANS:
            raise refuse(f"is corrupt: its compressed data holds marker 0xFF{marker:02X}, invalid there")
        if marker == _EOI:
            return
        if marker in (0x01, 0xD8):  # TEM, SOI: no length
            continue
        if pos + 2 > len(data):
            raise refuse("is truncated inside a segment length")
        length = int.from_bytes(data[pos : pos + 2])
        if length < 2:
            raise refuse(f"is malformed: segment 0xFF{marker:02X} has length {length}")
        yield marker, data[pos + 2 : pos + length]
        pos += length
        scanned = scanned or marker == _SOS


def _jpeg_header(data: bytes) -> ImageHeader:
    """The size from the first frame header (SOFn), as libjpeg takes it."""
    for marker, payload in _jpeg_segments(data, lambda why: InvalidInput(f"the JPEG image {why}")):
        if marker in _SOF_MARKERS:
            return _frame_header(marker, payload)
        if marker == _SOS:
            raise InvalidInput("the JPEG image is malformed: scan data (SOS) before the frame header")
    raise InvalidInput("the JPEG image ends (EOI) before its scan data")


def _frame_header(marker: int, payload: bytes) -> ImageHeader:
    if len(payload) < 6 or len(payload) < 6 + 3 * payload[5]:
        raise InvalidInput(f"the JPEG image is truncated inside its frame header (SOF{marker - 0xC0})")
    _precision, height, width, components = struct.unpack(">BHHB", payload[:6])
    if height == 0 or width == 0:
        raise InvalidInput(
            f"the JPEG image declares an unsupported size {width}x{height} "
            "(height defined later by a DNL marker is not supported)"
        )
    if components not in (1, 3, 4):
        raise InvalidInput(f"the JPEG image has {components} colour components; 1, 3 or 4 are supported")
    return ImageHeader("jpeg", width, height, components)


def _complete_jpeg_coefficient_bytes(data: bytes, header: ImageHeader) -> int:
    """Refuse a JPEG whose scans before EOI leave a DCT coefficient of a component out or short of
    full precision (a progressive scan with approximation bit Al > 0 needs a refinement down to
    0; lossless frames need each component in some scan). Return the bytes of libjpeg's buffer
    of every coefficient, which it fills for a progressive or multi-scan file (0 otherwise)."""
    frame, progressive, scans = b"", False, []
    for marker, payload in _jpeg_segments(data, lambda why: _corrupt(header, f"it {why}")):
        if marker in _SOF_MARKERS and not frame:
            frame, progressive = payload, marker in _PROGRESSIVE_SOF_MARKERS
        elif marker == _SOS:
            scans.append(payload)
    components = frame[6 : 6 + 3 * header.channels : 3]
    sampling = [(h >> 4, h & 0x0F) for h in frame[7 : 7 + 3 * header.channels : 3]]
    missing = {(c, k) for c in components for k in range(64 if progressive else 1)}
    for scan in scans:
        count = scan[0] if scan else 0
        if count == 0 or len(scan) < 4 + 2 * count:
            raise _corrupt(header, "it has a truncated scan header (SOS)")
        first, last, approximation = scan[1 + 2 * count : 4 + 2 * count]
        if not (progressive and approximation & 0x0F):
            delivered = range(first, min(last, 63) + 1) if progressive else (0,)
            missing -= {(c, k) for c in scan[1 : 1 + 2 * count : 2] for k in delivered}
    if missing:
        lacking = ", ".join(str(c) for c in sorted({c for c, _ in missing}))
        raise _corrupt(
            header,
            f"it is truncated: the data of component(s) {lacking} is incomplete at its end-of-image marker",
        )
    if not progressive and scans[0][0] == len(components):
        return 0
    # 64 2-byte coefficients per 8x8 block of each component, padded to whole MCUs
    mcu_columns = -(-header.width // (8 * max(max(h for h, _ in sampling), 1)))
    mcu_rows = -(-header.height // (8 * max(max(v for _, v in sampling), 1)))
    return 128 * sum(mcu_columns * h * mcu_rows * v for h, v in sampling)


def _decode_jpeg(data: bytes, header: ImageHeader) -> np.ndarray:
    colorspace = "GRAY" if header.channels == 1 else "BGR"
    try:
        image = simplejpeg.decode_jpeg(data, colorspace=colorspace, strict=True)
    except ValueError as exc:
        raise _corrupt(header, f"the file is corrupt or shorter than its size says (libjpeg: {exc})") from exc
    return image[:, :, 0] if header.channels == 1 else image
