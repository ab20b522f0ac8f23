"""Image sources: a whole frame, or regions of one, in full-frame pixel coordinates.

A region is resampled through the very affine the whole frame would be, from a frame-sized canvas
holding its pixels at their place (zeros elsewhere): answers are byte-identical to the whole
frame's, since the resampling reads only the box's crop context, which the region must cover.
"""

from __future__ import annotations

import hashlib
import threading
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass

import numpy as np

from service.detector.crop import CONTEXT_MARGIN_PX, crop_contexts, warp_crop
from service.detector.images import (
    ImageHeader,
    checked_image_header,
    decode_checked,
    decode_image,
    decode_jpeg_window,
    decoded_bytes,
    read_image_header,
)
from service.errors import InvalidInput, PayloadTooLarge

#: raw 8-bit encodings, as ROS sensor_msgs/Image names them, and their channels
RAW_CHANNELS = {"rgb8": 3, "bgr8": 3, "mono8": 1}
_canvases = threading.local()


@dataclass(frozen=True)
class EncodedRegion:
    """A rectangle of a frame as sent (ROS RegionOfInterest) and the instances it serves (None: all)."""

    x_offset: int
    y_offset: int
    width: int
    height: int
    encoding: str
    data: bytes | memoryview
    instances: tuple[int, ...] | None = None

    @property
    def name(self) -> str:
        return f"{self.width}x{self.height} region at ({self.x_offset}, {self.y_offset})"


@dataclass(frozen=True)
class EncodedFrame:
    """A frame of ``width`` x ``height`` pixels as sent: the whole of it, or regions."""

    width: int
    height: int
    regions: tuple[EncodedRegion, ...]
    whole: bool = False  # one region, the whole frame, serving every instance

    @classmethod
    def of_whole(cls, width: int, height: int, encoding: str, data: bytes | memoryview) -> EncodedFrame:
        return cls(width, height, (EncodedRegion(0, 0, width, height, encoding, data),), whole=True)

    def sha256(self) -> str:
        """What identifies the pixels sent: each region's place, size, encoding and bytes."""
        digest = hashlib.sha256(b"frame %d %d" % (self.width, self.height))
        for region in self.regions:
            place = (region.x_offset, region.y_offset, region.width, region.height)
            digest.update(b"region %d %d %d %d %s " % (*place, region.encoding.encode()))
            digest.update(region.data)
        return digest.hexdigest()


@dataclass(frozen=True)
class Region:
    """Decoded pixels of a frame's rectangle: gray, BGR, or RGB when ``rgb`` (reordered in the crops)."""

    x_offset: int
    y_offset: int
    pixels: np.ndarray
    rgb: bool = False
    instances: tuple[int, ...] | None = None


@dataclass(frozen=True)
class ImageSource:
    """A frame's pixels where the request has them: the whole frame, or regions of it."""

    width: int
    height: int
    regions: tuple[Region, ...]

    @classmethod
    def whole(cls, pixels: np.ndarray, rgb: bool = False) -> ImageSource:
        return cls(pixels.shape[1], pixels.shape[0], (Region(0, 0, pixels, rgb),))

    @property
    def pixels(self) -> np.ndarray:
        """The whole frame's pixels (BGR or gray); ``ValueError`` for a source of regions."""
        region = self.regions[0]
        if not self._is_whole(region):
            raise ValueError("the request sent regions of the frame, not the whole frame")
        return region.pixels[..., ::-1] if region.rgb else region.pixels

    def crops(self, affines: np.ndarray, size: tuple[int, int]) -> np.ndarray:
        """``(N, h, w, C)`` uint8 crops, BGR or gray, one per image -> crop affine."""
        gray = self.regions[0].pixels.ndim == 2
        crops = np.empty((len(affines), *size, 1 if gray else 3), dtype=np.uint8)
        for region in self.regions:
            served = range(len(affines)) if region.instances is None else region.instances
            with self._placed(region) as image:
                for i in served:
                    crop = warp_crop(image, affines[i], size).reshape(crops.shape[1:])
                    crops[i] = crop[..., ::-1] if region.rgb else crop
        return crops

    def _is_whole(self, region: Region) -> bool:
        return region.pixels.shape[:2] == (self.height, self.width)

    @contextmanager
    def _placed(self, region: Region) -> Iterator[np.ndarray]:
        """The region's pixels at their place in a frame of zeros, on the thread's canvas (zeroed again
        after use: a fresh one would pay a page fault per row the region touches)."""
        if self._is_whole(region):
            yield region.pixels
            return
        shape = (self.height, self.width, *region.pixels.shape[2:])
        canvas = getattr(_canvases, "canvas", None)
        if canvas is None or canvas.shape != shape:
            canvas = _canvases.canvas = np.zeros(shape, dtype=np.uint8)
        height, width = region.pixels.shape[:2]
        window = canvas[region.y_offset : region.y_offset + height, region.x_offset : region.x_offset + width]
        window[...] = region.pixels
        try:
            yield canvas
        finally:
            window[...] = 0


def image_source(data: bytes, header: ImageHeader, boxes: np.ndarray | None, padding: float) -> ImageSource:
    """An image file's pixels that the crops of ``boxes`` read: of a JPEG, one window around their
    crop contexts; the whole image for a PNG, a CMYK JPEG, or where ``boxes`` is None."""
    window = None
    if boxes is not None and len(boxes):
        contexts = crop_contexts(boxes, padding, header.width, header.height)
        x0, y0 = (int(v) for v in contexts[:, :2].min(axis=0))
        x1, y1 = (int(v) for v in contexts[:, 2:].max(axis=0))
        if x0 < x1 and y0 < y1:
            window = decode_jpeg_window(data, header, (x0, y0, x1, y1))
    if window is None:
        return ImageSource.whole(decode_checked(data, header))
    return ImageSource(header.width, header.height, (Region(window.x, window.y, window.pixels),))


def open_frame(
    frame: EncodedFrame, boxes: np.ndarray, padding: float, max_pixels: int, max_bytes: int
) -> ImageSource:
    """Check the frame's regions against the frame, the (checked) boxes and the limits, then decode them."""
    _check_frame_size(frame, max_pixels)
    problems = [problem for region in frame.regions for problem in _placement_problems(frame, region)]
    if not problems:
        contexts = crop_contexts(boxes, padding, frame.width, frame.height)
        problems = _service_problems(frame, contexts, padding)
    if problems:
        raise InvalidInput("; ".join(problems[:5]), errors=problems)
    _check_budget(frame, max_bytes)
    if frame.whole and frame.regions[0].encoding == "jpeg":  # only the window its boxes need
        data = frame.regions[0].data
        return image_source(data, checked_image_header(data, max_pixels, max_bytes), boxes, padding)
    whole_limit = max_bytes if frame.whole else None  # a whole PNG: decode_image checks it
    regions = tuple(_decoded(region, max_pixels, whole_limit) for region in frame.regions)
    if len({region.pixels.ndim for region in regions}) > 1:
        raise InvalidInput(
            "the regions mix gray and colour pixels: a frame's regions are all one or the other"
        )
    return ImageSource(frame.width, frame.height, regions)


def _check_frame_size(frame: EncodedFrame, max_pixels: int) -> None:
    if frame.width <= 0 or frame.height <= 0:
        raise InvalidInput(f"the frame's width and height must be positive, got {frame.width}x{frame.height}")
    pixels = frame.width * frame.height
    if pixels > max_pixels:
        raise PayloadTooLarge(
            f"the frame is {frame.width}x{frame.height} = {pixels} pixels, above the limit of {max_pixels}"
            " pixels (CKS_MAX_IMAGE_PIXELS); send a smaller frame"
        )


def _placement_problems(frame: EncodedFrame, region: EncodedRegion) -> list[str]:
    """What is wrong with where a region lies and with its bytes, read from its header only."""
    x, y, width, height = region.x_offset, region.y_offset, region.width, region.height
    if min(x, y) < 0 or width <= 0 or height <= 0:
        return [f"the {region.name}: offsets must be >= 0 and width and height > 0"]
    if x + width > frame.width or y + height > frame.height:
        return [
            f"the {region.name} reaches x = {x + width}, y = {y + height}, outside the"
            f" {frame.width}x{frame.height} frame: x_offset + width <= {frame.width} and"
            f" y_offset + height <= {frame.height}"
        ]
    channels = RAW_CHANNELS.get(region.encoding)
    if channels is not None:
        expected = width * height * channels
        if len(region.data) != expected:
            return [
                f"the {region.name} in {region.encoding} has {len(region.data)} bytes; its shape"
                f" {height}x{width}x{channels} (height x width x channels, row-major) needs {expected} bytes"
            ]
        return []
    header = read_image_header(region.data)
    if header.format != region.encoding:
        return [
            f"the {region.name} says encoding {region.encoding} but its bytes are a {header.format.upper()}"
        ]
    if (header.width, header.height) != (width, height):
        return [
            f"the {region.name}'s {header.format.upper()} is {header.width}x{header.height}: a region's"
            " width and height are its image's"
        ]
    return []


def _service_problems(frame: EncodedFrame, contexts: np.ndarray, padding: float) -> list[str]:
    """Every instance served by exactly one region that holds its crop context."""
    if frame.whole:
        return []
    count = len(contexts)
    serving: dict[int, list[int]] = {}
    problems = []
    for r, region in enumerate(frame.regions):
        for i in region.instances or ():
            if not 0 <= i < count:
                problems.append(f"regions[{r}].instances names instance {i}; there are {count} instances")
            else:
                serving.setdefault(i, []).append(r)
    for i in range(count):
        regions = serving.get(i, [])
        if len(regions) != 1:
            some = "no region serves" if not regions else f"regions {regions} all serve"
            problems.append(f"{some} instances[{i}]: list each instance in exactly one region's instances")
        else:
            problems.extend(_missing_margins(frame, regions[0], i, contexts[i], padding))
    return problems


def _missing_margins(frame: EncodedFrame, r: int, i: int, context: np.ndarray, padding: float) -> list[str]:
    region = frame.regions[r]
    x0, y0, x1, y1 = (int(v) for v in context)
    missing = {
        "left": region.x_offset - x0,
        "top": region.y_offset - y0,
        "right": x1 - (region.x_offset + region.width),
        "bottom": y1 - (region.y_offset + region.height),
    }
    short = ", ".join(f"{pixels} px on the {side}" for side, pixels in missing.items() if pixels > 0)
    if not short:
        return []
    return [
        f"regions[{r}] ({region.name}) misses {short} of instances[{i}]'s crop context x {x0}..{x1},"
        f" y {y0}..{y1} (the box's square crop, side max(w, h) * (1 + {padding:g}), widened by"
        f" {CONTEXT_MARGIN_PX} px, clipped to the {frame.width}x{frame.height} frame): send a larger region"
    ]


def _check_budget(frame: EncodedFrame, max_bytes: int) -> None:
    if frame.whole and frame.regions[0].encoding not in RAW_CHANNELS:
        return  # decode_image checks it, reading the file's segments once
    needed = sum(_decoded_size(region) for region in frame.regions)
    if needed > max_bytes:
        what = "the frame" if frame.whole else f"the {len(frame.regions)} regions"
        raise PayloadTooLarge(
            f"decoding {what} would take {needed} bytes of memory, above the limit of {max_bytes} bytes"
            " per image; send smaller regions"
        )


def _decoded_size(region: EncodedRegion) -> int:
    if channels := RAW_CHANNELS.get(region.encoding):
        return region.width * region.height * channels
    return decoded_bytes(region.data, read_image_header(region.data))


def _decoded(region: EncodedRegion, max_pixels: int, max_bytes: int | None) -> Region:
    channels = RAW_CHANNELS.get(region.encoding)
    if channels is None:
        pixels = decode_image(region.data, max_pixels, max_bytes)
    else:
        shape = (region.height, region.width) if channels == 1 else (region.height, region.width, channels)
        pixels = np.frombuffer(region.data, dtype=np.uint8).reshape(shape)
    return Region(region.x_offset, region.y_offset, pixels, region.encoding == "rgb8", region.instances)
