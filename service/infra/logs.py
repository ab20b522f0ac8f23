"""Logging: one format for the service's lines and uvicorn's, text or JSON, with the request id.

``uvicorn_log_config`` configures every logger that matters (one stderr handler on the root); a
filter puts the id of the request being handled (a context variable) on every record.
"""

from __future__ import annotations

import json
import logging
import logging.config
import re
import time
from collections.abc import Mapping
from contextvars import ContextVar
from dataclasses import dataclass
from typing import Any

from pythonjsonlogger.core import RESERVED_ATTRS

from service.infra.settings import Settings

TEXT_FORMAT = "%(asctime)s.%(msecs)03dZ %(levelname)s %(name)s [%(request_id)s] %(message)s"
LOGGERS = ("service", "calibration_store", "uvicorn", "uvicorn.error")
ACCESS_LOGGER = "service.access"
_PLAIN = re.compile(r'[^\s"\\=]+')  # a value written without quotes in a key=value line


@dataclass
class RequestContext:
    """What the log lines of one request share; the access line also says the calibration used."""

    request_id: str
    calibration_version: int | None = None


_request: ContextVar[RequestContext | None] = ContextVar("request", default=None)


def begin_request(request_id: str) -> RequestContext:
    """Make ``request_id`` the id of every line logged from now on in this context."""
    context = RequestContext(request_id)
    _request.set(context)
    return context


def current_request() -> RequestContext | None:
    return _request.get()


def note_calibration_version(version: int) -> None:
    """Record the calibration version that answered the current request (for its access line)."""
    if (context := _request.get()) is not None:
        context.calibration_version = version


class RequestIdFilter(logging.Filter):
    """Adds ``request_id`` to records logged while a request is handled."""

    def filter(self, record: logging.LogRecord) -> bool:
        if (context := _request.get()) is not None:
            record.request_id = context.request_id
        return True


class TextFormatter(logging.Formatter):
    """``2025-01-31T12:00:00.123Z INFO service.access [<request id>] message``, times in UTC."""

    converter = time.gmtime

    def __init__(self) -> None:
        super().__init__(TEXT_FORMAT, "%Y-%m-%dT%H:%M:%S", defaults={"request_id": "-"})


def _formatter(log_format: str) -> dict[str, Any]:
    if log_format == "json":
        # python-json-logger: the record's extra fields (request_id, an access line's or an
        # audit entry's fields) become members, exceptions one escaped string, one object a line.
        return {
            "()": "pythonjsonlogger.json.JsonFormatter",
            "fmt": "%(levelname)s %(name)s %(message)s",
            "rename_fields": {"levelname": "level", "name": "logger"},
            "timestamp": True,
            "reserved_attrs": [*RESERVED_ATTRS, "color_message"],  # uvicorn's ANSI copy of the message
        }
    return {"()": TextFormatter}


def uvicorn_log_config(settings: Settings, level: str | None = None) -> dict[str, Any]:
    """The dictConfig of the service's and uvicorn's loggers; ``level`` overrides ``CKS_LOG_LEVEL``.
    uvicorn's access log stays off: ``service.access`` writes one line per request instead."""
    level = level or settings.logs.level
    stderr = {"class": "logging.StreamHandler", "stream": "ext://sys.stderr", "formatter": "service"}
    return {
        "version": 1,
        "disable_existing_loggers": False,
        "filters": {"request_id": {"()": RequestIdFilter}},
        "formatters": {"service": _formatter(settings.logs.format)},
        "handlers": {"stderr": stderr | {"filters": ["request_id"]}},
        "root": {"handlers": ["stderr"], "level": "WARNING"},
        "loggers": {
            # handlers []: uvicorn's own (from its default config) are dropped, lines go to the root's
            **{name: {"handlers": [], "level": level, "propagate": True} for name in LOGGERS},
            # No handler and no propagation: uvicorn then skips its access lines altogether.
            "uvicorn.access": {"handlers": [], "propagate": False},
            ACCESS_LOGGER: {"level": level if settings.logs.access_log else "WARNING"},
        },
    }


def configure_logging(settings: Settings, level: str | None = None) -> None:
    """Apply ``uvicorn_log_config`` to this process."""
    logging.config.dictConfig(uvicorn_log_config(settings, level))


def ensure_logging(settings: Settings) -> None:
    """Configure logging unless the process already did (a ``--log-config`` of uvicorn, a host)."""
    if not logging.getLogger().handlers:
        configure_logging(settings)


def log_fields(
    logger: logging.Logger, event: str, fields: Mapping[str, Any], level: int = logging.INFO
) -> None:
    """One line ``event key=value ...`` (in JSON, members of the line's object); fields that are
    None or empty are left out."""
    present = {key: value for key, value in fields.items() if value is not None and value != ""}
    logger.log(level, "%s %s", event, " ".join(f"{k}={_text(v)}" for k, v in present.items()), extra=present)


def _text(value: object) -> str:
    if isinstance(value, Mapping | list):
        return json.dumps(value, sort_keys=True, separators=(",", ":"), default=str)
    text = str(value)
    return text if _PLAIN.fullmatch(text) and text.isprintable() else json.dumps(text)
