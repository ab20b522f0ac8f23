"""What the live and unit tests send a server to fault it, besides load (benchmarks/load.py): huge
images that are small on the wire, a zip bomb, a long calibration batch; and the peak resident
memory of a process, to see what they cost it.
"""

from __future__ import annotations

import io
import json
import struct
import zipfile
import zlib
from collections.abc import Callable
from pathlib import Path, PurePosixPath
from typing import Any

import cv2
import numpy as np

from benchmarks.load import SAMPLES_DIR
from service.detector.images import PNG_SIGNATURE

# ---------------------------------------------------------------- huge images


def flat_png(width: int, height: int, depth: int = 16, colour_type: int = 6) -> bytes:
    """A valid PNG of a repeated striped row: huge once decoded, small on the wire (one row is
    compressed at a time, so building it needs little memory)."""
    channels = {0: 1, 2: 3, 4: 2, 6: 4}[colour_type]
    stripes = np.arange(width * channels, dtype=np.uint32) % 251 * 257
    row = b"\x00" + stripes.astype(">u2" if depth == 16 else np.uint8).tobytes()
    compressor, idat = zlib.compressobj(6), []
    for _ in range(height):
        idat.append(compressor.compress(row))
    idat.append(compressor.flush())
    header = struct.pack(">IIBBBBB", width, height, depth, colour_type, 0, 0, 0)
    return (
        PNG_SIGNATURE
        + png_chunk(b"IHDR", header)
        + png_chunk(b"IDAT", b"".join(idat))
        + png_chunk(b"IEND", b"")
    )


def png_chunk(kind: bytes, payload: bytes) -> bytes:
    return struct.pack(">I", len(payload)) + kind + payload + struct.pack(">I", zlib.crc32(kind + payload))


def peak_rss_bytes(pid: int) -> int:
    """The peak resident memory of a process since its last ``reset_peak_rss`` (VmHWM)."""
    status = Path(f"/proc/{pid}/status").read_text()
    return 1024 * int(next(line.split()[1] for line in status.splitlines() if line.startswith("VmHWM:")))


def reset_peak_rss(pid: int) -> None:
    Path(f"/proc/{pid}/clear_refs").write_text("5")


def peak_while(pid: int, action: Callable[[], Any]) -> tuple[int, Any]:
    """The rise of the process's peak resident memory while ``action()`` runs, and its result."""
    reset_peak_rss(pid)
    before = peak_rss_bytes(pid)
    result = action()
    return peak_rss_bytes(pid) - before, result


# ---------------------------------------------------------------- uploads


def zip_bomb(uncompressed: int, name: str = "images/bomb.png") -> bytes:
    """A real zip bomb: ``annotations.json`` and one member of ``uncompressed`` zero bytes (a
    multiple of 16 MiB) with honest headers, deflated to about a thousandth of that."""
    block = 1 << 24
    assert uncompressed % block == 0, "a multiple of 16 MiB"
    compressor = zlib.compressobj(9, zlib.DEFLATED, -15)
    # After a full flush no block refers back to earlier data, so the same bytes can repeat.
    unit = compressor.compress(bytes(block)) + compressor.flush(zlib.Z_FULL_FLUSH)
    data = unit * (uncompressed // block) + compressor.flush()
    crc = 0
    for _ in range(uncompressed // block):
        crc = zlib.crc32(bytes(block), crc)
    annotations = json.dumps({"images": [], "annotations": [], "categories": []}).encode()
    buffer = io.BytesIO()
    with zipfile.ZipFile(buffer, "w") as archive:
        archive.writestr("annotations.json", annotations)
    small = buffer.getvalue()
    end = small.rindex(b"PK\x05\x06")
    directory_at = struct.unpack("<I", small[end + 16 : end + 20])[0]
    local_at = directory_at
    encoded = name.encode()
    zip64 = struct.pack("<HHQQ", 1, 16, uncompressed, len(data))
    sizes = (0xFFFFFFFF, 0xFFFFFFFF, len(encoded), len(zip64))  # the real ones are in the zip64 field
    local = struct.pack("<IHHHHHIIIHH", 0x04034B50, 45, 0, 8, 0, 0x21, crc, *sizes)
    central = struct.pack(
        "<IHHHHHHIIIHHHHHII", 0x02014B50, 45, 45, 0, 8, 0, 0x21, crc, *sizes, 0, 0, 0, 0, local_at
    )
    new_directory_at = local_at + len(local) + len(encoded) + len(zip64) + len(data)
    directory = small[directory_at:end] + central + encoded + zip64
    eocd = struct.pack("<IHHHHIIH", 0x06054B50, 0, 0, 2, 2, len(directory), new_directory_at, 0)
    return small[:directory_at] + local + encoded + zip64 + data + directory + eocd


def long_batch(copies: int) -> bytes:
    """A COCO zip of the bundled samples ``copies`` times over, each copy re-encoded at another
    JPEG quality so that no two files are the same (repeats would be refused)."""
    doc = json.loads((SAMPLES_DIR / "annotations.json").read_text())
    images, annotations = list(doc["images"]), list(doc["annotations"])
    files = {image["file_name"]: (SAMPLES_DIR / image["file_name"]).read_bytes() for image in images}
    next_image = max(image["id"] for image in images) + 1
    next_annotation = max(a["id"] for a in annotations) + 1
    for copy in range(1, copies):
        for image in images:
            path = PurePosixPath(image["file_name"])
            name = str(path.with_name(f"copy{copy}-{path.name}"))
            pixels = cv2.imdecode(np.frombuffer(files[image["file_name"]], np.uint8), cv2.IMREAD_COLOR)
            quality = [cv2.IMWRITE_JPEG_QUALITY, 95 - copy % 60]
            files[name] = cv2.imencode(".jpg", pixels, quality)[1].tobytes()
            doc["images"].append({**image, "id": next_image, "file_name": name})
            for annotation in (a for a in annotations if a["image_id"] == image["id"]):
                doc["annotations"].append({**annotation, "id": next_annotation, "image_id": next_image})
                next_annotation += 1
            next_image += 1
    buffer = io.BytesIO()
    with zipfile.ZipFile(buffer, "w") as archive:
        archive.writestr("annotations.json", json.dumps(doc))
        for name, data in files.items():
            archive.writestr(name, data)
    return buffer.getvalue()
