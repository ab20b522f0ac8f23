"""Images as the service takes them: JPEG or PNG files. Bytes and files are sent as they are;
numpy arrays are encoded here as lossless PNG (the stdlib's zlib, no imaging library)."""

from __future__ import annotations

import os
import struct
import zlib
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any, Literal, Union

from keypoint_client._numpy import np, require_numpy

if TYPE_CHECKING:
    from numpy.typing import NDArray

# Bytes of a JPEG or PNG file, a path to one, or pixels: (H, W) gray, (H, W, C) with C = 1..4,
# uint8 or uint16. numpy is optional, so its array type is a forward reference.
ImageInput = Union[bytes, bytearray, memoryview, str, "os.PathLike[str]", "NDArray[Any]"]  # noqa: UP007
ChannelOrder = Literal["rgb", "bgr"]

PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"
_PNG_COLOUR_TYPES = {1: 0, 2: 4, 3: 2, 4: 6}  # channels -> gray, gray+alpha, RGB, RGBA


@dataclass(frozen=True)
class EncodedImage:
    data: bytes
    filename: str
    content_type: str


def encode_image(image: ImageInput, channel_order: ChannelOrder = "rgb") -> EncodedImage:
    """The file to send; ``channel_order`` says how a numpy array's colour channels are ordered
    (``"bgr"`` for OpenCV's arrays)."""
    if isinstance(image, bytes | bytearray | memoryview):
        data = bytes(image)
        return EncodedImage(data, "image" + _suffix(data), _content_type(data))
    if isinstance(image, str | os.PathLike):
        path = Path(image)
        data = path.read_bytes()
        return EncodedImage(data, path.name, _content_type(data))
    return EncodedImage(png_bytes(image, channel_order), "image.png", "image/png")


def _suffix(data: bytes) -> str:
    return {"image/png": ".png", "image/jpeg": ".jpg"}.get(_content_type(data), "")


def _content_type(data: bytes) -> str:
    if data.startswith(PNG_SIGNATURE):
        return "image/png"
    if data.startswith(b"\xff\xd8"):
        return "image/jpeg"
    return "application/octet-stream"  # the service names what it accepts


def png_bytes(pixels: NDArray[Any], channel_order: ChannelOrder = "rgb") -> bytes:
    """A PNG file of ``pixels``: (H, W) or (H, W, C) with C in 1..4 (gray, gray + alpha, colour,
    colour + alpha), uint8 or uint16. Each row is stored with PNG's "Up" filter."""
    require_numpy("a numpy image")
    array = np.asarray(pixels)
    if array.ndim == 2:
        array = array[:, :, None]
    if array.ndim != 3 or array.shape[2] not in _PNG_COLOUR_TYPES or 0 in array.shape:
        raise ValueError(f"an image array must be (H, W) or (H, W, C) with C in 1..4, not {array.shape}")
    if array.dtype not in (np.uint8, np.uint16):
        raise ValueError(f"an image array must be uint8 or uint16, not {array.dtype} (convert it first)")
    if channel_order == "bgr" and array.shape[2] >= 3:
        array = np.concatenate([array[:, :, 2::-1], array[:, :, 3:]], axis=2)
    height, width, channels = array.shape
    big_endian = np.ascontiguousarray(array.astype(array.dtype.newbyteorder(">")))
    rows = big_endian.view(np.uint8).reshape(height, -1)
    filtered = rows.copy()
    filtered[1:] -= rows[:-1]  # "Up": each byte minus the one above, modulo 256
    raw = np.concatenate([np.full((height, 1), 2, dtype=np.uint8), filtered], axis=1).tobytes()
    depth = 8 * array.dtype.itemsize
    header = struct.pack(">IIBBBBB", width, height, depth, _PNG_COLOUR_TYPES[channels], 0, 0, 0)
    idat = zlib.compress(raw, 6)
    return PNG_SIGNATURE + _chunk(b"IHDR", header) + _chunk(b"IDAT", idat) + _chunk(b"IEND", b"")


def _chunk(kind: bytes, data: bytes) -> bytes:
    return struct.pack(">I", len(data)) + kind + data + struct.pack(">I", zlib.crc32(kind + data))
