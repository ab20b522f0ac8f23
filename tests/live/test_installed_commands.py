"""The commands as people start them, each a process: the installed ``keypoint-service`` entry point
(its --version, and mistakes answered as its main answers them in process), and uvicorn started
directly on the app, which exits non-zero naming what is wrong with the model's manifest.

Everything else about the commands runs their main in this process (tests/cli_calls.py).
"""

from __future__ import annotations

import importlib.metadata
import subprocess
import sys
from collections.abc import Callable
from pathlib import Path

import pytest

from service import __version__
from service.infra.settings import PACKAGE_ROOT
from tests.cli_calls import assert_one_line_error, run, run_installed
from tests.live.server import free_port, service_env
from tests.live.test_manifest_contract_cli import duplicate_name, edited_model
from tests.live.test_model_mismatch import mismatched_model
from tests.samples import model_dir
from tests.unit.test_cli_errors import MISTAKES


def test_version_is_the_package_version(tmp_path: Path) -> None:
    assert __version__ == importlib.metadata.version("conformal-keypoint-service")  # one source
    result = run_installed(["--version"], tmp_path / "data")
    assert (result.returncode, result.stdout, result.stderr) == (0, f"keypoint-service {__version__}\n", "")


@pytest.mark.parametrize(("args", "status", "fragments"), [MISTAKES[0], MISTAKES[-2]])
def test_the_installed_command_answers_the_same(
    tmp_path: Path, args: list[str], status: int, fragments: list[str]
) -> None:
    in_process = assert_one_line_error(run(args, tmp_path / "data"), status, *fragments)
    assert assert_one_line_error(run_installed(args, tmp_path / "data"), status, *fragments) == in_process


def mismatched_output_name(tmp_path: Path) -> tuple[Path, list[str]]:
    model = tmp_path / "model"
    return model, ["ModelMismatch", *mismatched_model(model_dir(), model, "output name")]


def duplicate_keypoint_name(tmp_path: Path) -> tuple[Path, list[str]]:
    model, expected = edited_model(tmp_path, duplicate_name)
    return model, [expected]


@pytest.mark.parametrize("broken", [mismatched_output_name, duplicate_keypoint_name])
def test_uvicorn_exits_non_zero_naming_what_is_wrong(
    tmp_path: Path, broken: Callable[[Path], tuple[Path, list[str]]]
) -> None:
    model, fragments = broken(tmp_path)
    port = str(free_port())
    command = [
        sys.executable,
        "-m",
        "uvicorn",
        "service.serving.main:app",
        "--host",
        "127.0.0.1",
        "--port",
        port,
    ]
    env = service_env(tmp_path / "data", model_dir=model)
    result = subprocess.run(command, env=env, cwd=PACKAGE_ROOT, capture_output=True, text=True, timeout=60)
    output = result.stdout + result.stderr
    assert result.returncode != 0, output
    for fragment in fragments:
        assert fragment in output, f"{fragment!r} not in: {output}"
