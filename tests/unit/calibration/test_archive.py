"""Upload streaming and safe extraction of calibration zips, with crafted malicious archives."""

from __future__ import annotations

import hashlib
import io
import struct
import warnings
import zipfile
from pathlib import Path

import pytest

from service.calibration import archive
from service.calibration.archive import (
    ArchiveLimits,
    BudgetExceeded,
    SavedUpload,
    UploadSink,
    copy_limited,
    extract_zip,
)
from service.errors import InvalidInput, PayloadTooLarge

LIMITS = ArchiveLimits(max_files=50, max_uncompressed_bytes=1_000_000)
ANNOTATIONS = b'{"images": [], "categories": [], "annotations": []}'


def make_zip(path: Path, members: list[tuple[str | zipfile.ZipInfo, bytes]]) -> Path:
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # zipfile warns about duplicate names
        with zipfile.ZipFile(path, "w", zipfile.ZIP_DEFLATED) as zf:
            for name, data in members:
                zf.writestr(name, data)
    return path


def entry(name: str, mode: int) -> zipfile.ZipInfo:
    info = zipfile.ZipInfo(name)
    info.create_system = 3  # unix
    info.external_attr = mode << 16
    return info


def patch_headers(path: Path, offset_local: int, offset_central: int, fmt: str, value: int) -> None:
    """Overwrite a field in every local and central directory header of the zip."""
    data = bytearray(path.read_bytes())
    for signature, offset in ((b"PK\x03\x04", offset_local), (b"PK\x01\x02", offset_central)):
        pos = data.find(signature)
        while pos >= 0:
            struct.pack_into(fmt, data, pos + offset, value)
            pos = data.find(signature, pos + 4)
    path.write_bytes(bytes(data))


@pytest.fixture
def dest(tmp_path: Path) -> Path:
    return tmp_path / "extracted"


def refused(kind: type[Exception], zip_path: Path, dest: Path, limits: ArchiveLimits = LIMITS) -> Exception:
    with pytest.raises(kind) as info:
        extract_zip(zip_path, dest, limits)
    assert not dest.exists(), "nothing may remain after a refusal"
    return info.value


class TestExtractGood:
    def test_annotations_at_root(self, tmp_path: Path, dest: Path) -> None:
        zip_path = make_zip(
            tmp_path / "b.zip",
            [("annotations.json", ANNOTATIONS), ("images/", b""), ("images/a.jpg", b"jpeg")],
        )
        folder = extract_zip(zip_path, dest, LIMITS)
        assert folder == dest.resolve() or folder == dest
        assert (folder / "annotations.json").read_bytes() == ANNOTATIONS
        assert (folder / "images" / "a.jpg").read_bytes() == b"jpeg"

    def test_annotations_in_single_top_folder(self, tmp_path: Path, dest: Path) -> None:
        zip_path = make_zip(
            tmp_path / "b.zip",
            [
                ("batch/annotations.json", ANNOTATIONS),
                ("batch/deep/er/a.png", b"png"),
                ("__MACOSX/batch/._a.png", b"junk"),
                (".DS_Store", b"junk"),
            ],
        )
        folder = extract_zip(zip_path, dest, LIMITS)
        assert folder.name == "batch" and (folder / "deep" / "er" / "a.png").read_bytes() == b"png"

    def test_existing_empty_destination_is_used(self, tmp_path: Path, dest: Path) -> None:
        dest.mkdir()
        zip_path = make_zip(tmp_path / "b.zip", [("annotations.json", ANNOTATIONS)])
        assert (extract_zip(zip_path, dest, LIMITS) / "annotations.json").is_file()

    def test_limits_are_inclusive(self, tmp_path: Path, dest: Path) -> None:
        zip_path = make_zip(tmp_path / "b.zip", [("annotations.json", ANNOTATIONS), ("x", b"12345")])
        extract_zip(zip_path, dest, ArchiveLimits(2, len(ANNOTATIONS) + 5))


class TestRefusedNames:
    @pytest.mark.parametrize(
        ("name", "reason"),
        [
            ("../x", "'..' component"),
            ("batch/../../x", "'..' component"),
            ("/etc/x", "absolute path"),
            ("C:/x", "drive letter"),
            ("c:x", "drive letter"),
            ("..\\x", "backslash"),
            ("batch\\..\\..\\x", "backslash"),
            ("a/./b", "'.' path component"),
            ("a//b", "empty or '.' path component"),
            ("a/" + "n" * 300, "longer than 255 bytes"),
        ],
    )
    def test_traversal(self, tmp_path: Path, dest: Path, name: str, reason: str) -> None:
        zip_path = make_zip(tmp_path / "b.zip", [("annotations.json", ANNOTATIONS), (name, b"evil")])
        error = refused(InvalidInput, zip_path, dest)
        assert f"member {name!r}" in error.detail and reason in error.detail
        assert not (tmp_path / "x").exists()

    def test_every_problem_is_listed_and_capped(self, tmp_path: Path, dest: Path) -> None:
        members = [(f"../x{i}", b"") for i in range(60)]
        error = refused(InvalidInput, make_zip(tmp_path / "b.zip", members), dest, ArchiveLimits(100, 10**6))
        assert len(error.errors) == archive.MAX_REPORTED_PROBLEMS + 1
        assert error.errors[-1] == "... and 10 more"
        assert "60 problem(s)" in error.detail

    def test_duplicate_names(self, tmp_path: Path, dest: Path) -> None:
        zip_path = make_zip(
            tmp_path / "b.zip", [("annotations.json", ANNOTATIONS), ("annotations.json", b"{}")]
        )
        error = refused(InvalidInput, zip_path, dest)
        assert "'annotations.json': the name appears more than once" in error.detail

    def test_file_and_folder_with_the_same_name(self, tmp_path: Path, dest: Path) -> None:
        zip_path = make_zip(
            tmp_path / "b.zip", [("annotations.json", ANNOTATIONS), ("a", b"1"), ("a/b", b"2")]
        )
        error = refused(InvalidInput, zip_path, dest)
        assert "'a': the name is used both as a file and as a folder" in error.detail


class TestRefusedEntries:
    def test_symlink(self, tmp_path: Path, dest: Path) -> None:
        link = entry("images/a.jpg", 0o120777)
        zip_path = make_zip(tmp_path / "b.zip", [("annotations.json", ANNOTATIONS), (link, b"/etc/passwd")])
        error = refused(InvalidInput, zip_path, dest)
        assert "'images/a.jpg': is a symbolic link" in error.detail

    @pytest.mark.parametrize(
        "mode", [0o010644, 0o020644, 0o060644, 0o140644], ids=["fifo", "chr", "blk", "sock"]
    )
    def test_special_files(self, tmp_path: Path, dest: Path, mode: int) -> None:
        zip_path = make_zip(
            tmp_path / "b.zip", [("annotations.json", ANNOTATIONS), (entry("dev", mode), b"")]
        )
        error = refused(InvalidInput, zip_path, dest)
        assert "'dev': is not a regular file" in error.detail

    def test_directory_mode_without_slash(self, tmp_path: Path, dest: Path) -> None:
        zip_path = make_zip(
            tmp_path / "b.zip", [("annotations.json", ANNOTATIONS), (entry("d", 0o040755), b"")]
        )
        assert "marked as a folder" in refused(InvalidInput, zip_path, dest).detail

    def test_regular_unix_modes_are_fine(self, tmp_path: Path, dest: Path) -> None:
        members = [(entry("annotations.json", 0o100644), ANNOTATIONS), (entry("images/", 0o040755), b"")]
        extract_zip(make_zip(tmp_path / "b.zip", members), dest, LIMITS)

    def test_encrypted(self, tmp_path: Path, dest: Path) -> None:
        zip_path = make_zip(tmp_path / "b.zip", [("annotations.json", ANNOTATIONS)])
        patch_headers(zip_path, 6, 8, "<H", 0x0001)  # general purpose flag bit 0
        error = refused(InvalidInput, zip_path, dest)
        assert "'annotations.json': is encrypted" in error.detail

    def test_unknown_compression(self, tmp_path: Path, dest: Path) -> None:
        zip_path = make_zip(tmp_path / "b.zip", [("annotations.json", ANNOTATIONS)])
        patch_headers(zip_path, 8, 10, "<H", 99)  # AES
        error = refused(InvalidInput, zip_path, dest)
        assert "compression method 99" in error.detail and "deflate" in error.detail


class TestRefusedArchives:
    @pytest.mark.parametrize("content", [b"", b"not a zip at all", b"PK\x03\x04" + b"\x00" * 40])
    def test_not_a_zip(self, tmp_path: Path, dest: Path, content: bytes) -> None:
        (tmp_path / "b.zip").write_bytes(content)
        assert "not a readable zip archive" in refused(InvalidInput, tmp_path / "b.zip", dest).detail

    def test_truncated_zip(self, tmp_path: Path, dest: Path) -> None:
        zip_path = make_zip(tmp_path / "b.zip", [("annotations.json", ANNOTATIONS * 100)])
        zip_path.write_bytes(zip_path.read_bytes()[:-30])
        refused(InvalidInput, zip_path, dest)

    def test_corrupt_member_data(self, tmp_path: Path, dest: Path) -> None:
        zip_path = make_zip(tmp_path / "b.zip", [("annotations.json", bytes(range(256)) * 40)])
        data = bytearray(zip_path.read_bytes())
        data[60:90] = b"\xff" * 30  # inside the compressed stream
        zip_path.write_bytes(bytes(data))
        error = refused(InvalidInput, zip_path, dest)
        assert "'annotations.json' is corrupt" in error.detail

    def test_too_many_files(self, tmp_path: Path, dest: Path) -> None:
        members = [("annotations.json", ANNOTATIONS)] + [(f"images/{i}.jpg", b"") for i in range(10)]
        error = refused(
            PayloadTooLarge, make_zip(tmp_path / "b.zip", members), dest, ArchiveLimits(10, 10**6)
        )
        assert "11 entries" in error.detail and "limit of 10" in error.detail

    def test_declared_size_above_limit(self, tmp_path: Path, dest: Path) -> None:
        members = [("annotations.json", ANNOTATIONS), ("bomb.bin", b"\x00" * 2_000_000)]
        zip_path = make_zip(tmp_path / "b.zip", members)
        assert zip_path.stat().st_size < 10_000  # highly compressible
        error = refused(PayloadTooLarge, zip_path, dest)
        assert "'bomb.bin'" in error.detail and "1000000" in error.detail
        assert "uncompressed size" in error.detail

    def test_lying_header_sizes(self, tmp_path: Path, dest: Path) -> None:
        zip_path = make_zip(tmp_path / "b.zip", [("annotations.json", b"\x00" * 2_000_000)])
        patch_headers(zip_path, 22, 24, "<I", 1000)  # uncompressed size: 1000 instead of 2 MB
        refused(InvalidInput, zip_path, dest)

    def test_bytes_written_are_counted_while_streaming(
        self, tmp_path: Path, dest: Path, monkeypatch: pytest.MonkeyPatch
    ) -> None:
        """Even if the declared sizes passed, extraction stops once the real bytes exceed the limit."""
        monkeypatch.setattr(archive, "_check_declared_size", lambda *_: None)
        members = [
            ("annotations.json", ANNOTATIONS),
            ("a.bin", b"\x00" * 600_000),
            ("b.bin", b"\x00" * 600_000),
        ]
        error = refused(PayloadTooLarge, make_zip(tmp_path / "b.zip", members), dest)
        assert "'b.bin'" in error.detail and "while extracting" in error.detail
        assert "uncompressed bytes" in error.detail

    def test_no_annotations(self, tmp_path: Path, dest: Path) -> None:
        zip_path = make_zip(tmp_path / "b.zip", [("images/a.jpg", b""), ("notes.txt", b"")])
        error = refused(InvalidInput, zip_path, dest)
        assert "annotations.json was not found" in error.detail and "images/, notes.txt" in error.detail

    def test_two_top_level_folders(self, tmp_path: Path, dest: Path) -> None:
        members = [("a/annotations.json", ANNOTATIONS), ("b/annotations.json", ANNOTATIONS)]
        refused(InvalidInput, make_zip(tmp_path / "b.zip", members), dest)

    def test_annotations_too_deep(self, tmp_path: Path, dest: Path) -> None:
        refused(InvalidInput, make_zip(tmp_path / "b.zip", [("a/b/annotations.json", ANNOTATIONS)]), dest)

    def test_non_empty_destination_is_left_alone(self, tmp_path: Path, dest: Path) -> None:
        dest.mkdir()
        (dest / "keep").write_text("mine")
        zip_path = make_zip(tmp_path / "b.zip", [("annotations.json", ANNOTATIONS)])
        with pytest.raises(FileExistsError):
            extract_zip(zip_path, dest, LIMITS)
        assert (dest / "keep").read_text() == "mine"


class TestCopyLimited:
    def test_reads_at_most_budget_plus_one(self) -> None:
        class Endless(io.RawIOBase):
            requested = 0

            def read(self, size: int = -1) -> bytes:
                self.requested += size
                return b"\x00" * size

        src, out = Endless(), io.BytesIO()
        with pytest.raises(BudgetExceeded):
            copy_limited(src, out, 3_000_000)
        assert src.requested == 3_000_001
        assert out.tell() <= 3_000_000

    def test_within_budget(self) -> None:
        out = io.BytesIO()
        assert copy_limited(io.BytesIO(b"abc"), out, 3) == 3 and out.getvalue() == b"abc"


class TestUploadSink:
    def test_chunks_are_written_and_hashed(self, tmp_path: Path) -> None:
        chunks = [b"abc", b"", b"def" * 1000]
        sink = UploadSink(tmp_path / "u.zip", 10_000)
        for chunk in chunks:
            sink.write(chunk)
        assert sink.finish() == SavedUpload(3003, hashlib.sha256(b"".join(chunks)).hexdigest())
        assert (tmp_path / "u.zip").read_bytes() == b"".join(chunks)

    def test_too_large(self, tmp_path: Path) -> None:
        sink = UploadSink(tmp_path / "u.zip", 100)
        sink.write(b"x" * 60)
        with pytest.raises(PayloadTooLarge) as info:
            sink.write(b"x" * 60)
        assert "100 bytes" in info.value.detail and "CKS_MAX_UPLOAD_BYTES" in info.value.detail
        assert not (tmp_path / "u.zip").exists()

    def test_abort_removes_the_partial_file(self, tmp_path: Path) -> None:
        sink = UploadSink(tmp_path / "u.zip", 100)
        sink.write(b"partial")
        sink.abort()
        assert not (tmp_path / "u.zip").exists()
