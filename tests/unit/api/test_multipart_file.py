"""FilePart takes one part out of a multipart body however its bytes are cut on the way."""

from __future__ import annotations

import pytest

from service.api.http.multipart_file import FilePart
from service.errors import InvalidInput

ZIP = bytes(range(256)) * 40  # any bytes, CR and LF included
BODY = (
    b'--cut\r\nContent-Disposition: form-data; name="file"; filename="batch.zip"\r\n'
    b"Content-Type: application/zip\r\n\r\n" + ZIP + b"\r\n--cut--\r\n"
)


@pytest.mark.parametrize("piece", [1, 7, 64, len(BODY)])
def test_the_part_comes_out_whole_from_pieces_of_any_size(piece: int) -> None:
    out = bytearray()
    form = FilePart("multipart/form-data; boundary=cut", "file", out.extend)
    for start in range(0, len(BODY), piece):
        form.write(BODY[start : start + piece])
    form.finish()
    assert bytes(out) == ZIP


def test_a_part_of_another_name_is_refused_even_in_pieces() -> None:
    form = FilePart("multipart/form-data; boundary=cut", "archive", bytearray().extend)
    with pytest.raises(InvalidInput, match="unexpected multipart part 'file'"):
        for start in range(0, len(BODY), 3):
            form.write(BODY[start : start + 3])
