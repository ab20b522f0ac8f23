"""Corrupt or truncated images, in process: a 422 problem naming the fault, in predict and calibration.

Issue 12 item 4: a JPEG with a valid header and garbage scan data was scored and stored as
a calibration image. Issue 13 item 3: a JPEG whose header says 6000x6000 over 640x480 of
data answered 200 with ``width: 6000``.
"""

from __future__ import annotations

import struct
import zlib
from collections.abc import Callable
from pathlib import Path

import cv2
import numpy as np
import pytest

from tests.api.in_process import InProcess
from tests.predict_client import predict_json, predict_multipart
from tests.samples import batch_files, build_zip
from tests.service_calls import assert_problem


def scan_data(data: bytes) -> tuple[int, int]:
    """(start, end) of the entropy-coded data of a single-scan JPEG; end is the EOI's offset."""
    sos = data.find(b"\xff\xda")
    (length,) = struct.unpack(">H", data[sos + 2 : sos + 4])
    return sos + 2 + length, data.rfind(b"\xff\xd9")


def garbage_in_scan(data: bytes, size: int = 4000) -> bytes:
    """Random bytes over the middle of the scan data; headers and EOI intact."""
    start, end = scan_data(data)
    middle = (start + end) // 2
    noise = np.random.default_rng(0).integers(0, 256, size, dtype=np.uint8).tobytes()
    return data[:middle] + noise + data[middle + size :]


def zeros_in_scan(data: bytes) -> bytes:
    start, end = scan_data(data)
    middle = (start + end) // 2
    return data[:middle] + bytes(64) + data[middle + 64 :]


def claims_6000x6000(data: bytes) -> bytes:
    sof = data.find(b"\xff\xc0") + 5  # marker (2), length (2), precision (1)
    return data[:sof] + struct.pack(">HH", 6000, 6000) + data[sof + 4 :]


def truncated_with_end_marker(data: bytes) -> bytes:
    start, end = scan_data(data)
    return data[: (start + end) // 2] + b"\xff\xd9"


@pytest.mark.parametrize(
    ("corrupt", "fragments"),
    [
        (garbage_in_scan, ["JPEG image (640x480) cannot be decoded", "corrupt", "re-encode"]),
        (zeros_in_scan, ["JPEG image (640x480) cannot be decoded", "Corrupt JPEG data", "re-encode"]),
        (
            claims_6000x6000,
            ["JPEG image (6000x6000) cannot be decoded", "shorter than its size", "re-encode"],
        ),
        (truncated_with_end_marker, ["premature end of data segment", "re-encode"]),
    ],
    ids=["garbage-scan", "zeroed-scan", "header-6000x6000", "truncated-with-eoi"],
)
@pytest.mark.parametrize("form", ["json", "multipart"])
def test_corrupt_jpeg_predict_is_422(
    api: InProcess,
    sample: tuple[bytes, list[dict]],
    corrupt: Callable[[bytes], bytes],
    fragments: list[str],
    form: str,
) -> None:
    image, instances = sample
    send = predict_json if form == "json" else predict_multipart
    response = send(api.client, corrupt(image), {"instances": instances})
    assert_problem(response, 422, *fragments)
    assert send(api.client, image, {"instances": instances}).status_code == 200  # the original is fine


def test_png_with_a_corrupted_chunk_crc_is_422(api: InProcess, sample: tuple[bytes, list[dict]]) -> None:
    image, instances = sample
    ok, encoded = cv2.imencode(".png", cv2.imdecode(np.frombuffer(image, np.uint8), cv2.IMREAD_COLOR))
    assert ok
    png = encoded.tobytes()
    idat = png.find(b"IDAT")
    (length,) = struct.unpack(">I", png[idat - 4 : idat])
    crc_at = idat + 4 + length
    assert struct.unpack(">I", png[crc_at : crc_at + 4])[0] == zlib.crc32(png[idat : idat + 4 + length])
    broken = png[:crc_at] + bytes(b ^ 0xFF for b in png[crc_at : crc_at + 4]) + png[crc_at + 4 :]
    response = predict_json(api.client, broken, {"instances": instances})
    assert_problem(response, 422, "PNG image (640x480) cannot be decoded", "IDAT chunk", "CRC")


def test_corrupt_calibration_image_fails_the_job_and_stores_nothing(
    api: InProcess, samples_dir: Path, coco: dict
) -> None:
    """Issue 12: the garbage-scan JPEG was scored and stored; now its job fails, naming the file."""
    versions = api.versions()
    active = api.client.get("/readyz").json()["active_calibration"]
    doc, files = batch_files(samples_dir, coco, images=2)
    broken = doc["images"][1]["file_name"]
    files[broken] = garbage_in_scan(files[broken])
    response = api.upload(build_zip(doc, files), activate=True)
    assert response.status_code == 202, response.text  # header and size match: only decoding finds it
    job = api.wait_job(response.json()["id"])
    assert job["state"] == "failed", job
    errors = " ".join(job["errors"])
    assert broken in errors and "cannot be decoded" in errors and "corrupt" in errors, job["errors"]
    assert api.versions() == versions
    assert api.client.get("/readyz").json()["active_calibration"] == active
    assert api.upload_workspaces() == []
