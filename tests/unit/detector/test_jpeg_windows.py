"""A whole JPEG decoded in a window around its boxes (service/detector/native/jpeg_window.c):
the window's pixels are the full decode's, bit for bit, whatever the chroma subsampling, scan
mode or size, so crops and answers are the whole image's; corrupt data outside the window is
still refused; what cannot be windowed is decoded whole."""

from __future__ import annotations

import struct
from dataclasses import replace

import cv2
import numpy as np
import pytest

from service.detector.crop import crop_affines
from service.detector.frames import ImageSource, image_source
from service.detector.images import (
    checked_image_header,
    decode_image,
    decode_jpeg_window,
    jpeg_windows_available,
    read_image_header,
)
from service.errors import InvalidInput, PayloadTooLarge, UnsupportedMediaType
from service.infra.settings import DEFAULT_MODEL_DIR

SAMPLES = sorted((DEFAULT_MODEL_DIR / "samples" / "images").glob("*.jpg"))
LIMIT = 50_000_000
#: OpenCV's sampling factors: 4:4:4, 4:2:2, 4:2:0, 4:1:1
SAMPLINGS = {"444": 0x111111, "422": 0x211111, "420": 0x221111, "411": 0x411111}


def test_the_extension_is_built() -> None:
    assert jpeg_windows_available(), (
        "service/detector/_jpeg_window*.so is missing or was built from older sources: install libjpeg's"
        " headers and a C compiler (apt install libjpeg-dev gcc) and rerun pip install -e ."
    )


def _encodings() -> dict[str, bytes]:
    """The bundled samples, and one of them at an odd size in every subsampling, progressive, gray."""
    files = {path.name: path.read_bytes() for path in SAMPLES[:4]}
    image = cv2.resize(cv2.imread(str(SAMPLES[0])), (1917, 1079))
    for name, factor in SAMPLINGS.items():
        for progressive in (0, 1):
            options = [cv2.IMWRITE_JPEG_QUALITY, 90, cv2.IMWRITE_JPEG_SAMPLING_FACTOR, factor]
            options += [cv2.IMWRITE_JPEG_PROGRESSIVE, progressive]
            files[f"{name}, progressive {progressive}"] = cv2.imencode(".jpg", image, options)[1].tobytes()
    files["gray"] = cv2.imencode(".jpg", cv2.cvtColor(image, cv2.COLOR_BGR2GRAY))[1].tobytes()
    return files


@pytest.mark.parametrize(("name", "data"), list(_encodings().items()))
def test_a_window_holds_the_full_decodes_pixels(name: str, data: bytes) -> None:
    whole = decode_image(data, LIMIT)
    header = read_image_header(data)
    height, width = whole.shape[:2]
    rng = np.random.default_rng(len(data))
    for _ in range(60):
        x0, x1 = sorted(int(v) for v in rng.choice(width + 1, 2, replace=False))
        y0, y1 = sorted(int(v) for v in rng.choice(height + 1, 2, replace=False))
        window = decode_jpeg_window(data, header, (x0, y0, x1, y1))
        assert window is not None
        assert window.x <= x0 and window.y <= y0
        inside = window.pixels[y0 - window.y : y1 - window.y, x0 - window.x : x1 - window.x]
        assert np.array_equal(inside, whole[y0:y1, x0:x1]), (name, (x0, y0, x1, y1))


def _scan_data(data: bytes) -> tuple[int, int]:
    sos = data.find(b"\xff\xda")
    (length,) = struct.unpack(">H", data[sos + 2 : sos + 4])
    return sos + 2 + length, data.rfind(b"\xff\xd9")


def test_corrupt_data_below_and_above_the_window_is_refused() -> None:
    data = SAMPLES[0].read_bytes()
    header = read_image_header(data)
    start, end = _scan_data(data)
    for offset in (start + 200, end - 40):  # in the first rows, in the last
        corrupt = data[:offset] + bytes(32) + data[offset + 32 :]
        with pytest.raises(InvalidInput, match="Corrupt JPEG data"):
            decode_jpeg_window(corrupt, header, (300, 200, 340, 240))


def test_a_window_refuses_a_damaged_jpeg_exactly_when_the_full_decode_does() -> None:
    """1 to 3 random bytes changed anywhere (headers, tables, scan data), 600 times: both decoders
    refuse the file, or both decode it to the same pixels in the window."""
    rng = np.random.default_rng(7)
    files = [path.read_bytes() for path in SAMPLES]
    window = (200, 150, 400, 350)
    outcomes = []
    for case in range(600):
        data = bytearray(files[case % len(files)])
        for _ in range(rng.integers(1, 4)):
            data[int(rng.integers(2, len(data)))] = int(rng.integers(0, 256))
        try:
            header = checked_image_header(bytes(data), LIMIT)
        except (InvalidInput, PayloadTooLarge, UnsupportedMediaType):
            continue  # refused before any decoding, as by decode_image
        if header.width < 400 or header.height < 350:
            continue  # a damaged size: the window is outside it
        try:
            whole = decode_image(bytes(data), LIMIT)
        except InvalidInput:
            whole = None
        try:
            decoded = decode_jpeg_window(bytes(data), header, window)
        except InvalidInput:
            decoded = None
        assert (whole is None) == (decoded is None), case
        if decoded is not None and whole is not None:
            inside = decoded.pixels[150 - decoded.y : 350 - decoded.y, 200 - decoded.x : 400 - decoded.x]
            assert np.array_equal(inside, whole[150:350, 200:400]), case
        outcomes.append(whole is None)
    assert 0 < sum(outcomes) < len(outcomes)  # some damage refused, some harmless


def test_the_crops_of_a_windowed_source_are_the_whole_images() -> None:
    data = SAMPLES[1].read_bytes()
    header = checked_image_header(data, LIMIT)
    boxes = np.array([[200.0, 150.0, 60.0, 80.0], [420.0, 300.0, 40.0, 30.0]])
    source = image_source(data, header, boxes, 0.25)
    assert len(source.regions) == 1 and source.regions[0].pixels.shape[:2] != (480, 640)  # a window
    affines = crop_affines(boxes, 0.25, (128, 128))
    expected = ImageSource.whole(decode_image(data, LIMIT)).crops(affines, (128, 128))
    assert np.array_equal(source.crops(affines, (128, 128)), expected)


def test_a_png_a_cmyk_jpeg_and_a_drawing_get_the_whole_image() -> None:
    jpeg = SAMPLES[0].read_bytes()
    png = cv2.imencode(".png", decode_image(jpeg, LIMIT))[1].tobytes()
    boxes = np.array([[200.0, 150.0, 60.0, 80.0]])
    for data, wanted in ((png, boxes), (jpeg, None)):  # a drawing of the sets asks for no boxes
        source = image_source(data, checked_image_header(data, LIMIT), wanted, 0.25)
        assert np.array_equal(source.pixels, decode_image(data, LIMIT))
    cmyk = replace(read_image_header(jpeg), channels=4)  # libjpeg turns CMYK into no BGR
    assert decode_jpeg_window(jpeg, cmyk, (0, 0, 8, 8)) is None
