"""What the tests of generated clients (tests/live/test_*client*.py) share: the server they drive
(on a loopback port, served by a thread of the test's process) and the import of a freshly
generated package."""

from __future__ import annotations

import importlib
import sys
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from types import ModuleType

from tests.api.in_process import OnLoopback
from tests.service_calls import ADMIN_TOKEN

MAX_REQUEST_BYTES = 1_000_000  # small, so that a client's 413 is within reach


def generated_client_server(data_dir: Path) -> OnLoopback:
    """An admin token, no calibration yet (predict answers 503 until one is activated) and a small
    request limit."""
    settings = {"bootstrap_calibration": False, "max_request_bytes": MAX_REQUEST_BYTES}
    return OnLoopback(data_dir, admin_token=ADMIN_TOKEN, **settings)


@contextmanager
def imported_package(directory: Path, package: str, modules: list[str]) -> Iterator[list[ModuleType]]:
    """The package's modules (``package.name``, or the package for ""), imported from directory and
    forgotten afterwards (the next generation imports afresh)."""
    sys.path.insert(0, str(directory))
    try:
        yield [importlib.import_module(f"{package}.{name}" if name else package) for name in modules]
    finally:
        sys.path.remove(str(directory))
        for name in [m for m in sys.modules if m == package or m.startswith(f"{package}.")]:
            del sys.modules[name]
