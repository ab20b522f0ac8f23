"""A numpy frame as POST /v1/predict/frame takes it: each box's region (its crop context, the
service's crop rule) as raw pixels, a JPEG or a PNG, or the whole frame raw. No JPEG of the
whole frame at either end: the service answers as it would for the whole frame's pixels."""

from __future__ import annotations

import json
import math
from collections.abc import Sequence
from typing import TYPE_CHECKING, Any, Literal, TypeGuard

from keypoint_client._numpy import np, require_numpy
from keypoint_client.images import ChannelOrder, png_bytes

if TYPE_CHECKING:
    from numpy.typing import NDArray

    from keypoint_client.models import ModelInfo

# How a numpy frame is sent: its boxes' regions raw (the default), as JPEG (lossy: the answer is
# the JPEG's) or PNG files, or the whole frame raw.
FrameSending = Literal["regions", "jpeg-regions", "png-regions", "raw-frame"]
CONTEXT_MARGIN_PX = 2  # the service's: pixels beyond a crop's square its resampling may read
JPEG_QUALITY = 95
Part = tuple[str, tuple[str | None, bytes, str]]
Rectangle = tuple[int, int, int, int]  # x0, y0, x1, y1: columns x0 .. x1 - 1, rows y0 .. y1 - 1


def is_frame(image: object) -> TypeGuard[NDArray[Any]]:
    """A numpy array of uint8 pixels, (H, W), (H, W, 1) or (H, W, 3): what a frame is sent as."""
    if np is None or not isinstance(image, np.ndarray) or image.dtype != np.uint8 or 0 in image.shape:
        return False
    return image.ndim == 2 or (image.ndim == 3 and image.shape[2] in (1, 3))


def crop_padding(model: ModelInfo) -> float:
    """The served model's crop padding (its manifest's ``crop.padding``), which sizes the regions."""
    return model.manifest.crop.padding


def crop_context(bbox: Sequence[float], padding: float, width: int, height: int) -> Rectangle:
    """``(x0, y0, x1, y1)``, half-open, of the pixels the service resamples a box's crop from:
    the square of side max(w, h) * (1 + padding) centred on the box, widened by
    ``CONTEXT_MARGIN_PX`` and clipped to the frame."""
    x, y, w, h = (float(v) for v in bbox)
    half = max(w, h) * (1.0 + padding) / 2
    cx, cy = x + w / 2, y + h / 2
    x0, y0 = math.floor(cx - half) - CONTEXT_MARGIN_PX, math.floor(cy - half) - CONTEXT_MARGIN_PX
    x1, y1 = math.ceil(cx + half) + CONTEXT_MARGIN_PX, math.ceil(cy + half) + CONTEXT_MARGIN_PX
    return max(0, min(x0, width)), max(0, min(y0, height)), max(0, min(x1, width)), max(0, min(y1, height))


def frame_parts(
    frame: NDArray[Any],
    parameters: dict[str, Any],
    padding: float,
    sending: FrameSending = "regions",
    channel_order: ChannelOrder = "rgb",
) -> list[Part]:
    """The multipart parts of POST /v1/predict/frame: ``request`` (``parameters`` with the frame
    and its regions) and one ``pixels`` part per region (or the whole frame)."""
    require_numpy("a numpy frame")
    pixels = frame[:, :, 0] if frame.ndim == 3 and frame.shape[2] == 1 else frame
    height, width = pixels.shape[:2]
    raw = "mono8" if pixels.ndim == 2 else f"{channel_order}8"
    if sending == "raw-frame":
        request = {**parameters, "frame": {"width": width, "height": height, "encoding": raw}}
        return [_json(request), _pixels(pixels.tobytes(), "application/octet-stream")]
    regions, parts = [], []
    for (x0, y0, x1, y1), served in _rectangles(parameters["instances"], padding, width, height):
        encoding, data, kind = _encoded(pixels[y0:y1, x0:x1], sending, raw, channel_order)
        regions.append(
            {"x_offset": x0, "y_offset": y0, "width": x1 - x0, "height": y1 - y0, "encoding": encoding}
            | {"instances": served}
        )
        parts.append(_pixels(data, kind))
    request = {**parameters, "frame": {"width": width, "height": height}, "regions": regions}
    return [_json(request), *parts]


def _rectangles(
    instances: Sequence[dict[str, Any]], padding: float, width: int, height: int
) -> list[tuple[Rectangle, list[int]]]:
    """One rectangle per box's crop context, but boxes whose contexts overlap share one where
    the rectangle around both has no more pixels than the two apart."""
    merged: list[tuple[Rectangle, list[int]]] = []
    for i, instance in enumerate(instances):
        box = crop_context(instance["bbox"], padding, width, height)
        if box[2] <= box[0] or box[3] <= box[1]:  # a box outside the frame: the service names the problem
            box = (0, 0, min(width, 1), min(height, 1))
        for k, (other, served) in enumerate(merged):
            both = (
                min(box[0], other[0]),
                min(box[1], other[1]),
                max(box[2], other[2]),
                max(box[3], other[3]),
            )
            if _area(both) <= _area(box) + _area(other):
                merged[k] = (both, [*served, i])
                break
        else:
            merged.append((box, [i]))
    return merged


def _area(rectangle: Rectangle) -> int:
    return (rectangle[2] - rectangle[0]) * (rectangle[3] - rectangle[1])


def _encoded(
    region: NDArray[Any], sending: FrameSending, raw: str, order: ChannelOrder
) -> tuple[str, bytes, str]:
    if sending == "png-regions":
        return "png", png_bytes(region, order), "image/png"
    if sending == "jpeg-regions":
        return "jpeg", jpeg_bytes(region, order), "image/jpeg"
    return raw, region.tobytes(), "application/octet-stream"  # C order, one copy


def jpeg_bytes(
    pixels: NDArray[Any], channel_order: ChannelOrder = "rgb", quality: int = JPEG_QUALITY
) -> bytes:
    """A JPEG of uint8 pixels, (H, W) or (H, W, 3), by libjpeg-turbo (``pip install simplejpeg``)."""
    try:
        import simplejpeg  # type: ignore[import-untyped]
    except ImportError as error:
        raise ImportError("JPEG regions need simplejpeg: pip install simplejpeg") from error
    image = np.ascontiguousarray(pixels if pixels.ndim == 3 else pixels[:, :, None])
    colorspace = "GRAY" if image.shape[2] == 1 else channel_order.upper()
    return bytes(simplejpeg.encode_jpeg(image, quality=quality, colorspace=colorspace))


def _json(request: dict[str, Any]) -> Part:
    return ("request", (None, json.dumps(request).encode(), "application/json"))


def _pixels(data: bytes, content_type: str) -> Part:
    return ("pixels", ("pixels", data, content_type))
