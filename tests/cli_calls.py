"""keypoint-service run as a test needs it: ``main`` in this process with a server's environment
(``run``), or the installed entry point as a process (``run_installed``)."""

from __future__ import annotations

import contextlib
import io
import logging
import os
import subprocess
from collections.abc import Iterator
from pathlib import Path
from typing import Any
from unittest import mock

from service.cli import main
from service.infra.settings import PACKAGE_ROOT
from tests.live.server import cli, service_env


def run(args: list[str], data_dir: Path, **settings: Any) -> subprocess.CompletedProcess:
    """``keypoint-service ARGS`` in this process, as a process would run it."""
    stdout, stderr = io.StringIO(), io.StringIO()
    env = service_env(data_dir, **settings)
    with (
        mock.patch.dict(os.environ, env, clear=True),
        _logging_restored(),
        contextlib.redirect_stdout(stdout),
        contextlib.redirect_stderr(stderr),
    ):
        try:
            status = main(args)
        except SystemExit as exit_:  # argparse: usage errors, --help, --version
            status = exit_.code if isinstance(exit_.code, int) else 1
    return subprocess.CompletedProcess(args, status, stdout.getvalue(), stderr.getvalue())


def run_installed(args: list[str], data_dir: Path, **settings: Any) -> subprocess.CompletedProcess:
    """The installed entry point, as a process."""
    env = service_env(data_dir, **settings)
    return subprocess.run(
        [*cli(), *args], env=env, cwd=PACKAGE_ROOT, capture_output=True, text=True, timeout=120
    )


@contextlib.contextmanager
def _logging_restored() -> Iterator[None]:
    """The command configures logging for its process: undone for the tests that follow."""
    root = logging.getLogger()
    handlers, level = root.handlers[:], root.level
    try:
        yield
    finally:
        root.handlers[:] = handlers
        root.setLevel(level)


def assert_one_line_error(result: subprocess.CompletedProcess, status: int, *fragments: str) -> str:
    output = f"exit {result.returncode}\nstdout:\n{result.stdout}\nstderr:\n{result.stderr}"
    assert result.returncode == status, output
    assert "Traceback" not in result.stderr, output
    lines = result.stderr.splitlines()
    assert len(lines) == 1 and "error: " in lines[0], output
    assert result.stdout == "", output
    for fragment in fragments:
        assert fragment in lines[0], f"{fragment!r} not in: {lines[0]}"
    return lines[0]
