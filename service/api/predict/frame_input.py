"""POST /v1/predict/frame bodies -> ``EncodedFrame`` and parameters; parts are cut out of the body in
place (one pass), so raw pixels reach the detector as views of it, never copied or spooled to disk."""

from __future__ import annotations

from service.api.http.multipart_file import MultipartParts
from service.api.predict.frame_schemas import FrameRequest
from service.api.predict.predict_input import validated
from service.detector.frames import RAW_CHANNELS, EncodedFrame, EncodedRegion
from service.detector.manifest import Manifest
from service.errors import InvalidInput, UnsupportedMediaType

REQUEST_PART, PIXELS_PART = "request", "pixels"
LAYOUT = (
    "send multipart/form-data with the part 'request' (JSON: instances, options, frame, regions) and"
    " one part 'pixels' per region, in the order of regions (or one, the whole frame)"
)


def require_multipart(content_type: str) -> None:
    """415 unless multipart/form-data (checked before the body is received)."""
    media = content_type.split(";")[0].strip().lower()
    if media != "multipart/form-data":
        raise UnsupportedMediaType(f"{LAYOUT}; not {media!r}")


def parse_frame(content_type: str, body: bytes, manifest: Manifest) -> tuple[EncodedFrame, FrameRequest]:
    """The frame and the parameters of a POST /v1/predict/frame body; 422 naming what to fix."""
    parts = _parts(content_type, body)
    names = [name for name, _ in parts]
    if names.count(REQUEST_PART) != 1 or set(names) - {REQUEST_PART, PIXELS_PART}:
        raise InvalidInput(f"the parts are {names}: {LAYOUT}")
    raw = next(bytes(data) for name, data in parts if name == REQUEST_PART)
    parameters = validated(FrameRequest, raw, manifest)
    pixels = [data for name, data in parts if name == PIXELS_PART]
    return _frame(parameters, pixels), parameters


def _frame(parameters: FrameRequest, pixels: list[bytes | memoryview]) -> EncodedFrame:
    frame, regions = parameters.frame, parameters.regions
    if (frame.encoding is None) == (regions is None):
        raise InvalidInput(
            "send either frame.encoding with the whole frame as the one 'pixels' part, or regions"
            " (each with its encoding) with one 'pixels' part per region, not both or neither"
        )
    expected = 1 if regions is None else len(regions)
    if len(pixels) != expected:
        what = "the whole frame" if regions is None else f"the {expected} regions, in order"
        raise InvalidInput(f"{len(pixels)} 'pixels' parts, for {what}: send {expected}")
    if regions is None:
        encoding = frame.encoding
        assert encoding is not None
        return EncodedFrame.of_whole(frame.width, frame.height, encoding, _data(encoding, pixels[0]))
    encoded = tuple(
        EncodedRegion(
            r.x_offset, r.y_offset, r.width, r.height, r.encoding, _data(r.encoding, data), tuple(r.instances)
        )
        for r, data in zip(regions, pixels, strict=True)
    )
    return EncodedFrame(frame.width, frame.height, encoded)


def _data(encoding: str, data: bytes | memoryview) -> bytes | memoryview:
    """Raw pixels stay a view of the body; a JPEG or PNG becomes bytes, as its decoders take it."""
    return data if encoding in RAW_CHANNELS else bytes(data)


class _Parts(MultipartParts):
    """Each part's name ("" for none) and pieces, in order: views of the body the parser was handed."""

    def __init__(self, content_type: str, body: bytes) -> None:
        super().__init__(content_type)
        self.parts: list[tuple[str, list]] = []
        self._body, self._whole = body, memoryview(body)

    def part_begins(self, name: str | None) -> None:
        self.parts.append((name or "", []))

    def part_data(self, data: bytes, start: int, end: int) -> None:
        self.parts[-1][1].append(self._whole[start:end] if data is self._body else bytes(data[start:end]))


def _parts(content_type: str, body: bytes) -> list[tuple[str, bytes | memoryview]]:
    """Each part's name and bytes, in order (a view of ``body`` where the part is one piece)."""
    parsed = _Parts(content_type, body)
    parsed.write(body)
    parsed.require_end()
    return [(name, pieces[0] if len(pieces) == 1 else b"".join(pieces)) for name, pieces in parsed.parts]
