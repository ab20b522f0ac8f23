"""The operator console: one page and its script and style, shipped in the package (no CDN). The files
are open; the data comes from the admin API, whose token the page asks for and keeps in sessionStorage."""

from __future__ import annotations

from pathlib import Path

from fastapi import APIRouter
from fastapi.responses import Response

from service.errors import NotFound

router = APIRouter(include_in_schema=False)

STATIC = Path(__file__).resolve().parents[2] / "console" / "static"
_MEDIA_TYPES = {"console.js": "text/javascript", "console.css": "text/css", "favicon.svg": "image/svg+xml"}
#: the page's own origin only, no inline script: the console needs nothing else
CONSOLE_CONTENT_SECURITY_POLICY = (
    "default-src 'none'; script-src 'self'; style-src 'self'; img-src 'self' data:; connect-src 'self'; "
    "base-uri 'none'; form-action 'none'; frame-ancestors 'none'"
)
_HEADERS = {"Content-Security-Policy": CONSOLE_CONTENT_SECURITY_POLICY, "Cache-Control": "no-cache"}


@router.get("/console")
async def console_page() -> Response:
    return Response((STATIC / "index.html").read_bytes(), media_type="text/html", headers=_HEADERS)


@router.get("/favicon.ico")
async def favicon() -> Response:
    """The service's icon, for browsers that ask for it on any page (SVG: they read the type)."""
    return await console_file("favicon.svg")


@router.get("/console/{name}")
async def console_file(name: str) -> Response:
    media_type = _MEDIA_TYPES.get(name)
    if media_type is None:
        raise NotFound(f"the console has no file {name!r}; open /console")
    return Response((STATIC / name).read_bytes(), media_type=media_type, headers=_HEADERS)
