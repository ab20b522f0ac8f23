"""The fast reading of plain multipart bodies (service/api/multipart.py) answers exactly as
Starlette's parser would, and leaves every other body to it.

Each body goes both ways through the predict route's own functions: the fast path, and
Starlette's ``request.form()``; where the fast path answers, both answers are equal, and it
must answer for what real clients send (httpx, urllib3, curl's layout).
"""

from __future__ import annotations

import asyncio
import json

import httpx
import pytest
import urllib3
from starlette.requests import Request

from service.api.routes.predict import _parse_multipart, _parse_plain_multipart
from service.errors import InvalidInput

PARAMETERS = json.dumps({"instances": [{"object": "ape", "bbox": [10, 20, 30, 40]}]})
IMAGE = bytes(range(256)) * 40 + b"\r\n--almost-a-boundary\r\n\r\r\n\n--"  # binary, CRs, dashes


def _request(body: bytes, content_type: str) -> Request:
    request = Request({"type": "http", "method": "POST", "path": "/v1/predict", "query_string": b"",
                       "headers": [(b"content-type", content_type.encode("latin-1"))]})  # fmt: skip
    request._body = body
    return request


def _by_starlette(body: bytes, content_type: str) -> tuple[bytes, object] | str:
    try:
        return asyncio.run(_parse_multipart(_request(body, content_type)))
    except InvalidInput as problem:
        return f"refused: {problem}"


def _form(boundary: str, parts: list[tuple[str, str | None, bytes]], newline: bytes = b"\r\n") -> bytes:
    body = b""
    for name, filename, data in parts:
        disposition = f'form-data; name="{name}"' + ("" if filename is None else f'; filename="{filename}"')
        body += b"--" + boundary.encode() + newline
        body += b"Content-Disposition: " + disposition.encode() + newline + newline + data + newline
    return body + b"--" + boundary.encode() + b"--" + newline


def _client_bodies() -> list[tuple[str, bytes, str]]:
    files = {"image": ("scene.jpg", IMAGE, "image/jpeg")}
    made = httpx.Request("POST", "http://x/v1/predict", files=files, data={"request": PARAMETERS})
    urllib3_body, urllib3_type = urllib3.encode_multipart_formdata(
        {"image": ("scene.jpg", IMAGE, "image/jpeg"), "request": PARAMETERS}
    )
    curl = _form("------------------------d74496d66958873e", [("request", None, PARAMETERS.encode()),
                                                            ("image", "scene.jpg", IMAGE)])  # fmt: skip
    return [
        ("httpx", made.read(), made.headers["content-type"]),
        ("urllib3", urllib3_body, urllib3_type),
        ("curl", curl, "multipart/form-data; boundary=------------------------d74496d66958873e"),
    ]


@pytest.mark.parametrize(("client", "body", "content_type"), _client_bodies(), ids=lambda v: str(v)[:12])
def test_what_clients_send_takes_the_fast_path_with_starlettes_answer(
    client: str, body: bytes, content_type: str
) -> None:
    fast = _parse_plain_multipart(_request(body, content_type), body)

    assert fast is not None
    assert fast == _by_starlette(body, content_type)
    assert fast[0] == IMAGE


B = "edge"
CT = f"multipart/form-data; boundary={B}"
PLAIN = [("image", "a.jpg", IMAGE), ("request", None, PARAMETERS.encode())]
UNUSUAL = {
    "quoted boundary": (_form(B, PLAIN), f'multipart/form-data; boundary="{B}"'),
    "epilogue": (_form(B, PLAIN) + b"trailing words", CT),
    "preamble": (b"preamble\r\n" + _form(B, PLAIN), CT),
    "LF line breaks": (_form(B, PLAIN, newline=b"\n"), CT),
    "charset": (_form(B, PLAIN), f"multipart/form-data; boundary={B}; charset=latin-1"),
    "no boundary": (_form(B, PLAIN), "multipart/form-data"),
    "no closing delimiter": (_form(B, PLAIN)[: -len(B) - 6], CT),
    "request as a file": (_form(B, [PLAIN[0], ("request", "r.json", PARAMETERS.encode())]),
                          CT),
    "image as a field": (_form(B, [("image", None, b"jpeg"), PLAIN[1]]), CT),
    "no image": (_form(B, PLAIN[1:]), CT),
    "no request": (_form(B, PLAIN[:1]), CT),
    "a third part": (_form(B, [*PLAIN, ("note", None, b"hi")]), CT),
    "two images": (_form(B, [*PLAIN, ("image", "b.jpg", b"x")]), CT),
    "not UTF-8": (_form(B, [PLAIN[0], ("request", None, b'{"instances": "\xff"}')]),
                  CT),
    "a delimiter in the data": (_form(B, [("image", "a.jpg", b"x\r\n--" + B.encode() + b"x"), PLAIN[1]]),
                                CT),
    "another header": (_form(B, PLAIN).replace(b"Content-Disposition: form-data; name=\"request\"",
                                               b"Content-Disposition: form-data; name=\"request\"\r\nX-A: b"),
                       CT),
    "no part headers": (b"--edge\r\n\r\nxyz\r\n--edge--\r\n", CT),
    "empty": (b"", CT),
}  # fmt: skip


@pytest.mark.parametrize("case", UNUSUAL)
def test_any_other_body_is_left_to_starlette(case: str) -> None:
    body, content_type = UNUSUAL[case]
    fast = _parse_plain_multipart(_request(body, content_type), body)

    if case == "quoted boundary":  # plain after all: read as Starlette reads it
        assert fast == _by_starlette(body, content_type)
    else:
        assert fast is None


def test_bad_parameters_in_a_plain_body_get_the_same_refusal() -> None:
    body = _form(B, [PLAIN[0], ("request", None, b'{"instances": []}')])
    content_type = CT

    with pytest.raises(InvalidInput) as fast:
        _parse_plain_multipart(_request(body, content_type), body)
    assert f"refused: {fast.value}" == _by_starlette(body, content_type)
