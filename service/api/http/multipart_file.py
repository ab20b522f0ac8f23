"""multipart/form-data bodies read as they stream through, part by part (``MultipartParts``), and
one file part taken out of a body never whole in memory, for the uploads that take a zip as a
form's file part (``FilePart``)."""

from __future__ import annotations

from collections.abc import Callable

from python_multipart.exceptions import MultipartParseError
from python_multipart.multipart import MultipartParser, parse_options_header

from service.errors import InvalidInput


class MultipartParts:
    """Feed it the body's bytes with ``write``: each part's name (None: it has none) goes to
    ``part_begins``, its bytes to ``part_data``; 422 for a malformed body."""

    def __init__(self, content_type: str) -> None:
        boundary = parse_options_header(content_type)[1].get(b"boundary")
        if not boundary:
            raise InvalidInput("multipart/form-data needs a boundary in its Content-Type")
        self._headers: list[bytes] = []
        self._value = bytearray()  # a header's value arrives in as many pieces as the body's chunks
        self._ended = False
        callbacks = {
            "on_part_begin": self._headers.clear,
            "on_header_value": lambda data, start, end: self._value.extend(data[start:end]),
            "on_header_end": self._header_end,
            "on_headers_finished": self._headers_finished,
            "on_part_data": self.part_data,
            "on_part_end": self.part_ends,
            "on_end": self._end,
        }
        self._parser = MultipartParser(boundary, callbacks)  # type: ignore[arg-type]

    def write(self, data: bytes) -> None:
        try:
            self._parser.write(data)
        except MultipartParseError as error:
            raise InvalidInput(f"malformed multipart body: {error}") from error

    def require_end(self) -> None:
        """422 unless the body ended with its closing boundary."""
        if not self._ended:
            raise InvalidInput("the multipart body ends before its closing boundary")

    def part_begins(self, name: str | None) -> None:
        raise NotImplementedError

    def part_data(self, data: bytes, start: int, end: int) -> None:
        raise NotImplementedError

    def part_ends(self) -> None:
        pass

    def _header_end(self) -> None:
        self._headers.append(bytes(self._value))
        self._value.clear()

    def _headers_finished(self) -> None:
        names = [parse_options_header(value)[1].get(b"name") for value in self._headers]
        self.part_begins(next((n.decode("utf-8", "replace") for n in names if n), None))

    def _end(self) -> None:
        self._ended = True


class FilePart(MultipartParts):
    """The bytes of the part named ``name`` go to ``out``. Any other part is refused (422), so a
    parameter sent as a form field is not silently ignored."""

    def __init__(self, content_type: str, name: str, out: Callable[[bytes], None]) -> None:
        super().__init__(content_type)
        self._name, self._out = name, out
        self._inside = self._found = False

    def finish(self) -> None:
        """422 unless the body ended properly with the part in it."""
        self.require_end()
        if not self._found:
            raise InvalidInput(f"multipart part {self._name!r} (the zip file) is missing")

    def part_begins(self, name: str | None) -> None:
        if name != self._name:
            raise InvalidInput(
                f"unexpected multipart part {name!r}: send the zip as the part {self._name!r}, and the"
                " parameters as query parameters"
            )
        if self._found:
            raise InvalidInput(f"multipart part {self._name!r} appears more than once")
        self._inside = self._found = True

    def part_data(self, data: bytes, start: int, end: int) -> None:
        if self._inside:
            self._out(data[start:end])

    def part_ends(self) -> None:
        self._inside = False
