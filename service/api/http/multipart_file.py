"""One file part of a multipart/form-data body, taken out as the body streams through (never the
whole body in memory), for the uploads that take a zip as a form's file part."""

from __future__ import annotations

from collections.abc import Callable

from python_multipart.exceptions import MultipartParseError
from python_multipart.multipart import MultipartParser, parse_options_header

from service.errors import InvalidInput


class FilePart:
    """Feed it the body's bytes with ``write``; the bytes of the part named ``name`` go to ``out``.
    Any other part is refused (422), so a parameter sent as a form field is not silently ignored."""

    def __init__(self, content_type: str, name: str, out: Callable[[bytes], None]) -> None:
        boundary = parse_options_header(content_type)[1].get(b"boundary")
        if not boundary:
            raise InvalidInput("multipart/form-data needs a boundary in its Content-Type")
        self._name, self._out = name, out
        self._headers: list[bytes] = []
        self._value = bytearray()  # a header's value arrives in as many pieces as the body's chunks
        self._inside = self._found = self._ended = False
        callbacks = {
            "on_part_begin": self._headers.clear,
            "on_header_value": self._header_piece,
            "on_header_end": self._header_end,
            "on_headers_finished": self._part_begins,
            "on_part_data": self._data,
            "on_part_end": self._part_ends,
            "on_end": self._end,
        }
        self._parser = MultipartParser(boundary, callbacks)  # type: ignore[arg-type]

    def write(self, data: bytes) -> None:
        try:
            self._parser.write(data)
        except MultipartParseError as error:
            raise InvalidInput(f"malformed multipart body: {error}") from error

    def finish(self) -> None:
        """422 unless the body ended properly with the part in it."""
        if not self._ended:
            raise InvalidInput("the multipart body ends before its closing boundary")
        if not self._found:
            raise InvalidInput(f"multipart part {self._name!r} (the zip file) is missing")

    def _header_piece(self, data: bytes, start: int, end: int) -> None:
        self._value += data[start:end]

    def _header_end(self) -> None:
        self._headers.append(bytes(self._value))
        self._value.clear()

    def _part_begins(self) -> None:
        names = [parse_options_header(value)[1].get(b"name") for value in self._headers]
        name = next((n.decode("utf-8", "replace") for n in names if n), None)
        if name != self._name:
            raise InvalidInput(
                f"unexpected multipart part {name!r}: send the zip as the part {self._name!r}, and the"
                " parameters as query parameters"
            )
        if self._found:
            raise InvalidInput(f"multipart part {self._name!r} appears more than once")
        self._inside = self._found = True

    def _data(self, data: bytes, start: int, end: int) -> None:
        if self._inside:
            self._out(data[start:end])

    def _part_ends(self) -> None:
        self._inside = False

    def _end(self) -> None:
        self._ended = True
