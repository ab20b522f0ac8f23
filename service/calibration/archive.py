"""Calibration uploads: stream to disk, then unzip safely within limits. Every member is checked
before anything is written; the bytes unzipped are counted, because a zip bomb's headers may lie.
"""

from __future__ import annotations

import contextlib
import hashlib
import os
import re
import shutil
import stat
import zipfile
import zlib
from dataclasses import dataclass
from pathlib import Path, PurePosixPath
from typing import BinaryIO, NamedTuple

from service.calibration.coco import ANNOTATIONS_FILENAME, MAX_REPORTED_PROBLEMS, check_annotations_size
from service.errors import InsufficientStorage, InvalidInput, PayloadTooLarge, capped

CHUNK_BYTES = 1 << 20
MAX_NAME_COMPONENT_BYTES = 255
#: most entries of an uploaded zip
MAX_UPLOAD_FILES = 100_000
#: most bytes an uploaded zip may hold once unzipped
MAX_UNCOMPRESSED_BYTES = 4 * 2**30
#: free space that unzipping an upload must leave in the data directory
MIN_FREE_DISK_BYTES = 2**30
_SUPPORTED_COMPRESSION = {
    zipfile.ZIP_STORED: "stored",
    zipfile.ZIP_DEFLATED: "deflate",
    zipfile.ZIP_BZIP2: "bzip2",
    zipfile.ZIP_LZMA: "lzma",
}
_DRIVE = re.compile(r"^[A-Za-z]:")
_CORRUPT = (zipfile.BadZipFile, EOFError, zlib.error, NotImplementedError, RuntimeError, ValueError)


@dataclass(frozen=True)
class DiskBudget:
    """What the uploads kept in ``folders`` may take in all, and the free space to leave."""

    folders: tuple[Path, ...]
    max_bytes: int
    min_free_bytes: int = MIN_FREE_DISK_BYTES

    def check(self, incoming: int, where: Path) -> None:
        """507 for ``incoming`` more bytes under ``where`` beyond the budget or the free space."""
        kept = sum(_tree_bytes(folder) for folder in self.folders)
        if kept + incoming > self.max_bytes:
            raise InsufficientStorage(
                f"unzipped, the upload would take {incoming} bytes; with the {kept} bytes that kept uploads"
                f" already take (of jobs queued, running or interrupted) that is above the budget of"
                f" {self.max_bytes} bytes (CKS_MAX_UPLOADS_DISK_BYTES): retry once jobs have finished"
            )
        free = shutil.disk_usage(where).free
        if free - incoming < self.min_free_bytes:
            raise InsufficientStorage(
                f"the data directory's file system has {free} bytes free: unzipping the upload's {incoming}"
                f" bytes would leave less than {self.min_free_bytes}"
            )


def _tree_bytes(folder: Path) -> int:
    total = 0
    for root, _, files in os.walk(folder):
        for name in files:
            with contextlib.suppress(FileNotFoundError):  # removed meanwhile by a finished job
                total += os.lstat(os.path.join(root, name)).st_size
    return total


@dataclass(frozen=True)
class ArchiveLimits:
    max_files: int = MAX_UPLOAD_FILES
    max_uncompressed_bytes: int = MAX_UNCOMPRESSED_BYTES


class SavedUpload(NamedTuple):
    size: int
    sha256: str


class UploadSink:
    """Writes an upload to disk chunk by chunk, hashing it and enforcing a size limit."""

    def __init__(self, dest_file: Path, max_bytes: int) -> None:
        self._dest, self._max = dest_file, max_bytes
        self._digest, self._size = hashlib.sha256(), 0
        self._out: BinaryIO = open(dest_file, "wb")  # noqa: SIM115 - closed by finish/abort

    def write(self, chunk: bytes) -> None:
        self._size += len(chunk)
        if self._size > self._max:
            self.abort()
            raise PayloadTooLarge(
                f"the upload is larger than the limit of {self._max} bytes (CKS_MAX_UPLOAD_BYTES); "
                "split the batch into smaller archives"
            )
        self._digest.update(chunk)
        self._out.write(chunk)

    def finish(self) -> SavedUpload:
        self._out.close()
        return SavedUpload(self._size, self._digest.hexdigest())

    def abort(self) -> None:
        self._out.close()
        self._dest.unlink(missing_ok=True)


def extract_zip(
    zip_path: Path, dest: Path, limits: ArchiveLimits = ArchiveLimits(), disk: DiskBudget | None = None
) -> Path:
    """Extract ``zip_path`` into ``dest`` (absent or empty) and return the folder holding
    ``annotations.json`` (``dest`` or its single top-level folder); a refusal removes ``dest``."""
    dest = Path(dest)
    if dest.exists() and any(dest.iterdir()):
        raise FileExistsError(f"extraction directory {dest} is not empty")
    dest.mkdir(parents=True, exist_ok=True)
    try:
        try:
            archive = zipfile.ZipFile(zip_path)
        except (zipfile.BadZipFile, zipfile.LargeZipFile, OSError, ValueError, EOFError) as exc:
            raise InvalidInput(
                f"the upload is not a readable zip archive ({exc});"
                " upload a .zip of annotations.json and images"
            ) from exc
        with archive:
            members = archive.infolist()
            _check_members(members, limits)
            if disk is not None:
                disk.check(sum(info.file_size for info in members), dest)
            _extract_members(archive, members, dest, limits.max_uncompressed_bytes)
        return _batch_folder(dest)
    except BaseException:
        shutil.rmtree(dest, ignore_errors=True)
        raise


def _check_members(members: list[zipfile.ZipInfo], limits: ArchiveLimits) -> None:
    if len(members) > limits.max_files:
        raise PayloadTooLarge(
            f"the archive has {len(members)} entries, above the limit of {limits.max_files}"
        )
    problems = [f"member {i.filename!r}: {p}" for i in members if (p := _member_problem(i))]
    problems.extend(_layout_problems(members))
    if problems:
        raise InvalidInput(
            f"the archive was refused ({len(problems)} problem(s)); first: {problems[0]}",
            errors=capped(problems, MAX_REPORTED_PROBLEMS),
        )
    _check_declared_size(members, limits.max_uncompressed_bytes)
    for info in members:  # before it is unzipped
        if PurePosixPath(info.filename).name == ANNOTATIONS_FILENAME:
            check_annotations_size(info.file_size, f"member {info.filename!r}")


def _check_declared_size(members: list[zipfile.ZipInfo], limit: int) -> None:
    total = 0
    for info in members:
        total += info.file_size
        if total > limit:
            raise PayloadTooLarge(
                f"member {info.filename!r} ({info.file_size} bytes) brings the archive's declared "
                f"uncompressed size to {total} bytes, above the limit of {limit} bytes"
            )


def _member_problem(info: zipfile.ZipInfo) -> str | None:
    name, kind = info.filename, stat.S_IFMT(info.external_attr >> 16)
    parts = name.rstrip("/").split("/")
    too_long = any(len(p.encode("utf-8", "surrogateescape")) > MAX_NAME_COMPONENT_BYTES for p in parts)
    methods, folder = ", ".join(_SUPPORTED_COMPRESSION.values()), info.is_dir()
    checks = (
        ("\\" in name, "contains a backslash; use '/' as the path separator"),
        ("\x00" in name, "contains a NUL character"),
        (name.startswith("/"), "is an absolute path; paths must be relative to the archive root"),
        (bool(_DRIVE.match(name)), "starts with a drive letter; paths must be relative to the archive root"),
        (".." in parts, "contains a '..' component (path traversal)"),
        (any(p in ("", ".") for p in parts), "contains an empty or '.' path component"),
        (too_long, f"has a path component longer than {MAX_NAME_COMPONENT_BYTES} bytes"),
        (kind == stat.S_IFLNK, "is a symbolic link; archives may contain only regular files and folders"),
        (kind not in (0, stat.S_IFREG, stat.S_IFDIR), "is not a regular file (device, pipe or socket entry)"),
        (kind == stat.S_IFDIR and not folder, "is marked as a folder but its name does not end with '/'"),
        (bool(info.flag_bits & 0x1), "is encrypted; upload an archive without a password"),
        (
            info.compress_type not in _SUPPORTED_COMPRESSION,
            f"uses compression method {info.compress_type}; supported: {methods}",
        ),
    )
    return next((problem for failed, problem in checks if failed), None)


def _layout_problems(members: list[zipfile.ZipInfo]) -> list[str]:
    """Duplicate names, and names used both as a file and as a folder."""
    problems: list[str] = []
    seen, files, folders = set[str](), set[str](), set[str]()
    for info in members:
        path = info.filename.rstrip("/")
        if path in seen:
            problems.append(f"member {info.filename!r}: the name appears more than once")
        seen.add(path)
        (folders if info.is_dir() else files).add(path)
        parts = path.split("/")
        folders.update("/".join(parts[:i]) for i in range(1, len(parts)))
    clashes = sorted(files & folders)
    return problems + [f"member {c!r}: the name is used both as a file and as a folder" for c in clashes]


def _extract_members(
    archive: zipfile.ZipFile, members: list[zipfile.ZipInfo], dest: Path, limit: int
) -> None:
    root = dest.resolve()
    written = 0
    for info in members:
        target = root / info.filename.rstrip("/")
        if not target.resolve().is_relative_to(root):  # defence in depth; names were checked
            raise InvalidInput(f"member {info.filename!r} would be written outside the batch folder")
        if info.is_dir():
            target.mkdir(parents=True, exist_ok=True)
            continue
        target.parent.mkdir(parents=True, exist_ok=True)
        try:
            with archive.open(info) as src, open(target, "xb") as out:
                written += copy_limited(src, out, limit - written)
        except BudgetExceeded as exc:
            raise PayloadTooLarge(
                f"member {info.filename!r} (declared {info.file_size} bytes) expanded past the limit of "
                f"{limit} uncompressed bytes while extracting: the archive's headers understate its size"
            ) from exc
        except _CORRUPT as exc:
            raise InvalidInput(
                f"member {info.filename!r} is corrupt and cannot be extracted ({exc}); rebuild the archive"
            ) from exc


class BudgetExceeded(Exception):
    """More bytes came out of a stream than the remaining budget allowed."""


def copy_limited(src: BinaryIO, out: BinaryIO, budget: int) -> int:
    """Copy ``src`` to ``out`` in 1 MiB chunks, reading at most ``budget + 1`` bytes whatever it claims."""
    written = 0
    while chunk := src.read(min(CHUNK_BYTES, budget - written + 1)):
        written += len(chunk)
        if written > budget:
            raise BudgetExceeded(f"more than {budget} bytes")
        out.write(chunk)
    return written


def _batch_folder(dest: Path) -> Path:
    if (dest / ANNOTATIONS_FILENAME).is_file():
        return dest
    top = [p for p in dest.iterdir() if p.name != "__MACOSX" and not p.name.startswith(".")]
    if len(top) == 1 and top[0].is_dir() and (top[0] / ANNOTATIONS_FILENAME).is_file():
        return top[0]
    found = ", ".join(sorted(p.name + ("/" if p.is_dir() else "") for p in top)[:10]) or "nothing"
    raise InvalidInput(
        f"{ANNOTATIONS_FILENAME} was not found at the archive root or inside a single top-level folder "
        f"(top level holds: {found}); put {ANNOTATIONS_FILENAME} next to the images"
    )
