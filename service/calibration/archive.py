"""Calibration uploads: stream to disk, then unzip safely within configured limits.

Every member of an uploaded zip is checked before anything is written (names, types,
encryption, counts, declared sizes), and the declared size against the disk: what kept
uploads may take together and the free space to leave (``DiskBudget``). Then members are
streamed to disk in bounded chunks while the bytes actually produced are counted, because
a zip bomb's headers may lie. Any refusal removes the destination directory entirely.
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

from service.calibration.coco import AnnotationLimits
from service.errors import InsufficientStorage, InvalidInput, PayloadTooLarge

ANNOTATIONS_FILENAME = "annotations.json"
CHUNK_BYTES = 1 << 20
MAX_REPORTED_PROBLEMS = 50
MAX_NAME_COMPONENT_BYTES = 255

UPLOAD_BYTES_SETTING = "CKS_MAX_UPLOAD_BYTES"
FILES_SETTING = "CKS_MAX_UPLOAD_FILES"
UNCOMPRESSED_SETTING = "CKS_MAX_UPLOAD_UNCOMPRESSED_BYTES"
DISK_BUDGET_SETTING = "CKS_MAX_UPLOADS_DISK_BYTES"
FREE_DISK_SETTING = "CKS_MIN_FREE_DISK_BYTES"

_SUPPORTED_COMPRESSION = {
    zipfile.ZIP_STORED: "stored",
    zipfile.ZIP_DEFLATED: "deflate",
    zipfile.ZIP_BZIP2: "bzip2",
    zipfile.ZIP_LZMA: "lzma",
}
_DRIVE = re.compile(r"^[A-Za-z]:")
_IGNORED_TOP_LEVEL = frozenset({"__MACOSX"})


@dataclass(frozen=True)
class DiskBudget:
    """Room on disk for unzipped uploads: what the uploads kept in ``folders`` may take in all
    (``max_bytes``), and the free space unzipping must leave on the file system."""

    folders: tuple[Path, ...]
    max_bytes: int
    min_free_bytes: int

    def check(self, incoming: int, where: Path) -> None:
        """Refuse (507) ``incoming`` more bytes under ``where`` beyond the budget or the free space."""
        kept = sum(_tree_bytes(folder) for folder in self.folders)
        if kept + incoming > self.max_bytes:
            raise InsufficientStorage(
                f"unzipped, the upload would take {incoming} bytes; with the {kept} bytes that kept uploads"
                f" already take (of jobs queued, running or interrupted) that is above the budget of"
                f" {self.max_bytes} bytes ({DISK_BUDGET_SETTING}): retry once jobs have finished"
            )
        free = shutil.disk_usage(where).free
        if free - incoming < self.min_free_bytes:
            raise InsufficientStorage(
                f"the data directory's file system has {free} bytes free: unzipping the upload's {incoming}"
                f" bytes would leave less than {self.min_free_bytes} ({FREE_DISK_SETTING})"
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
    """Most entries and most uncompressed bytes an uploaded archive may hold, and the limits of
    its annotations.json (None: unbounded)."""

    max_files: int
    max_uncompressed_bytes: int
    annotations: AnnotationLimits | None = None


class SavedUpload(NamedTuple):
    """An upload written to disk: its size in bytes and hex sha256."""

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
                f"the upload is larger than the limit of {self._max} bytes ({UPLOAD_BYTES_SETTING}); "
                "split the batch into smaller archives"
            )
        self._digest.update(chunk)
        self._out.write(chunk)

    def finish(self) -> SavedUpload:
        self._out.close()
        return SavedUpload(self._size, self._digest.hexdigest())

    def abort(self) -> None:
        """Close and delete the partial file."""
        self._out.close()
        self._dest.unlink(missing_ok=True)


def extract_zip(zip_path: Path, dest: Path, limits: ArchiveLimits, disk: DiskBudget | None = None) -> Path:
    """Safely extract ``zip_path`` into ``dest`` (absent or empty) and return the batch folder.

    The batch folder is the one holding ``annotations.json``: ``dest`` itself or its single
    top-level folder. Raises ``InvalidInput`` or ``PayloadTooLarge`` naming the offending
    member and the setting involved, ``InsufficientStorage`` when ``disk`` cannot take it
    (None: not checked); ``dest`` does not exist after a refusal.
    """
    dest = Path(dest)
    if dest.exists() and any(dest.iterdir()):
        raise FileExistsError(f"extraction directory {dest} is not empty")
    dest.mkdir(parents=True, exist_ok=True)
    try:
        with _open_zip(zip_path) as archive:
            members = archive.infolist()
            _check_members(members, limits)
            if disk is not None:
                disk.check(sum(info.file_size for info in members), dest)
            _extract_members(archive, members, dest, limits)
        return _batch_folder(dest)
    except BaseException:
        shutil.rmtree(dest, ignore_errors=True)
        raise


def _open_zip(zip_path: Path) -> zipfile.ZipFile:
    try:
        return zipfile.ZipFile(zip_path)
    except (zipfile.BadZipFile, zipfile.LargeZipFile, OSError, ValueError, EOFError) as exc:
        raise InvalidInput(
            f"the upload is not a readable zip archive ({exc}); upload a .zip of annotations.json and images"
        ) from exc


# ---------------------------------------------------------------- checks before writing


def _check_members(members: list[zipfile.ZipInfo], limits: ArchiveLimits) -> None:
    if len(members) > limits.max_files:
        raise PayloadTooLarge(
            f"the archive has {len(members)} entries, above the limit of {limits.max_files} ({FILES_SETTING})"
        )
    problems: list[str] = []
    for info in members:
        problem = _member_problem(info)
        if problem:
            problems.append(f"member {info.filename!r}: {problem}")
    problems.extend(_layout_problems(members))
    if problems:
        raise _refusal(problems)
    _check_declared_size(members, limits)
    for info in members if limits.annotations is not None else []:  # before it is unzipped
        if PurePosixPath(info.filename).name == ANNOTATIONS_FILENAME:
            limits.annotations.check_size(info.file_size, f"member {info.filename!r}")


def _refusal(problems: list[str]) -> InvalidInput:
    shown = problems[:MAX_REPORTED_PROBLEMS]
    if len(problems) > len(shown):
        shown.append(f"... and {len(problems) - len(shown)} more")
    return InvalidInput(
        f"the archive was refused ({len(problems)} problem(s)); first: {problems[0]}", errors=shown
    )


def _member_problem(info: zipfile.ZipInfo) -> str | None:
    """Why this member may not be extracted, or None."""
    return _name_problem(info.filename) or _type_problem(info) or _coding_problem(info)


def _name_problem(name: str) -> str | None:
    if "\\" in name:
        return "contains a backslash; use '/' as the path separator"
    if "\x00" in name:
        return "contains a NUL character"
    if name.startswith("/"):
        return "is an absolute path; paths must be relative to the archive root"
    if _DRIVE.match(name):
        return "starts with a drive letter; paths must be relative to the archive root"
    parts = name.rstrip("/").split("/")
    if any(p == ".." for p in parts):
        return "contains a '..' component (path traversal)"
    if any(p in ("", ".") for p in parts):
        return "contains an empty or '.' path component"
    if any(len(p.encode("utf-8", "surrogateescape")) > MAX_NAME_COMPONENT_BYTES for p in parts):
        return f"has a path component longer than {MAX_NAME_COMPONENT_BYTES} bytes"
    return None


def _type_problem(info: zipfile.ZipInfo) -> str | None:
    kind = stat.S_IFMT(info.external_attr >> 16)
    if kind == stat.S_IFLNK:
        return "is a symbolic link; archives may contain only regular files and folders"
    if kind not in (0, stat.S_IFREG, stat.S_IFDIR):
        return "is not a regular file (device, pipe or socket entry)"
    if kind == stat.S_IFDIR and not info.is_dir():
        return "is marked as a folder but its name does not end with '/'"
    return None


def _coding_problem(info: zipfile.ZipInfo) -> str | None:
    if info.flag_bits & 0x1:
        return "is encrypted; upload an archive without a password"
    if info.compress_type not in _SUPPORTED_COMPRESSION:
        methods = ", ".join(_SUPPORTED_COMPRESSION.values())
        return f"uses compression method {info.compress_type}; supported: {methods}"
    return None


def _layout_problems(members: list[zipfile.ZipInfo]) -> list[str]:
    """Duplicate names, and names used both as a file and as a folder."""
    problems: list[str] = []
    seen: set[str] = set()
    files: set[str] = set()
    folders: set[str] = set()
    for info in members:
        path = info.filename.rstrip("/")
        if path in seen:
            problems.append(f"member {info.filename!r}: the name appears more than once")
        seen.add(path)
        (folders if info.is_dir() else files).add(path)
        parts = path.split("/")
        folders.update("/".join(parts[:i]) for i in range(1, len(parts)))
    for clash in sorted(files & folders):
        problems.append(f"member {clash!r}: the name is used both as a file and as a folder")
    return problems


def _check_declared_size(members: list[zipfile.ZipInfo], limits: ArchiveLimits) -> None:
    total = 0
    for info in members:
        total += info.file_size
        if total > limits.max_uncompressed_bytes:
            raise PayloadTooLarge(
                f"member {info.filename!r} ({info.file_size} bytes) brings the archive's declared "
                f"uncompressed size to {total} bytes, above the limit of {limits.max_uncompressed_bytes} "
                f"bytes ({UNCOMPRESSED_SETTING})"
            )


# ---------------------------------------------------------------- streaming extraction


def _extract_members(
    archive: zipfile.ZipFile, members: list[zipfile.ZipInfo], dest: Path, limits: ArchiveLimits
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
        written += _extract_file(archive, info, target, written, limits.max_uncompressed_bytes)


def _extract_file(
    archive: zipfile.ZipFile, info: zipfile.ZipInfo, target: Path, written: int, limit: int
) -> int:
    """Copy one member in bounded chunks; return its size. ``written`` bytes came before it."""
    try:
        with archive.open(info) as src, open(target, "xb") as out:
            return copy_limited(src, out, limit - written)
    except BudgetExceeded as exc:
        raise PayloadTooLarge(
            f"member {info.filename!r} (declared {info.file_size} bytes) expanded past the limit of "
            f"{limit} uncompressed bytes ({UNCOMPRESSED_SETTING}) while extracting: the archive's "
            "headers understate its size"
        ) from exc
    except (zipfile.BadZipFile, EOFError, zlib.error, NotImplementedError, RuntimeError, ValueError) as exc:
        raise InvalidInput(
            f"member {info.filename!r} is corrupt and cannot be extracted ({exc}); rebuild the archive"
        ) from exc


class BudgetExceeded(Exception):
    """More bytes came out of a stream than the remaining budget allowed."""


def copy_limited(src: BinaryIO, out: BinaryIO, budget: int) -> int:
    """Copy ``src`` to ``out`` in chunks of at most 1 MiB; raise ``BudgetExceeded`` past ``budget``.

    At most ``budget + 1`` bytes are ever read, whatever ``src`` claims about its size.
    """
    written = 0
    while chunk := src.read(min(CHUNK_BYTES, budget - written + 1)):
        written += len(chunk)
        if written > budget:
            raise BudgetExceeded(f"more than {budget} bytes")
        out.write(chunk)
    return written


# ---------------------------------------------------------------- locating the batch


def _batch_folder(dest: Path) -> Path:
    if (dest / ANNOTATIONS_FILENAME).is_file():
        return dest
    top = [p for p in dest.iterdir() if p.name not in _IGNORED_TOP_LEVEL and not p.name.startswith(".")]
    if len(top) == 1 and top[0].is_dir() and (top[0] / ANNOTATIONS_FILENAME).is_file():
        return top[0]
    found = ", ".join(sorted(p.name + ("/" if p.is_dir() else "") for p in top)[:10]) or "nothing"
    raise InvalidInput(
        f"{ANNOTATIONS_FILENAME} was not found at the archive root or inside a single top-level folder "
        f"(top level holds: {found}); put {ANNOTATIONS_FILENAME} next to the images"
    )
