"""keypoint-service answers mistakes like a tool: one line on stderr, a non-zero exit status,
never a traceback; --version and every command's --help with examples.

The command's ``main`` runs in this process, with the environment a server process would get
(``service_env``) and its own stdout and stderr; the installed entry point, run as a process,
answers the same (tests/live/test_installed_commands.py)."""

from __future__ import annotations

import socket
from collections.abc import Iterator
from pathlib import Path

import pytest
from fastapi.testclient import TestClient

from service import __version__
from service.cli import EXAMPLES
from service.infra.settings import Settings
from service.serving.app import create_app
from tests.cli_calls import assert_one_line_error, run
from tests.live.server import free_port

SAMPLE_IMAGE = "models/lmo-synth-unet/samples/images/000000.jpg"
DUCK = "duck:235,217,67,64"


SAMPLES = "models/lmo-synth-unet/samples"
NO_SUCH = "no/such/"
# (arguments, exit status, fragments of the error line)
MISTAKES = [
    (["calibrate", f"{NO_SUCH}folder"], 2, [f"{NO_SUCH}folder is not a folder"]),
    (
        ["calibrate", SAMPLES, "--append-to", "two"],
        2,
        ["argument --append-to: invalid int value: 'two'", "(see keypoint-service calibrate --help)"],
    ),
    (["calibrate", SAMPLES, "--activate", "--force"], 2, ["force needs a reason"]),
    (["predict", f"{NO_SUCH}image.jpg", "--instance", DUCK], 1, [f"{NO_SUCH}image.jpg: No such file"]),
    (["predict", "README.md", "--instance", DUCK], 2, ["not a recognised image format"]),
    (["predict", SAMPLE_IMAGE], 2, ["the following arguments are required: --instance"]),
    (["predict", SAMPLE_IMAGE, "--instance", "duck:1,2,3"], 2, ["'duck:1,2,3': use OBJECT:x,y,w,h"]),
    (["predict", SAMPLE_IMAGE, "--instance", "duck:a,2,3,4"], 2, ["'duck:a,2,3,4': use OBJECT:x,y,w,h"]),
    (
        ["predict", SAMPLE_IMAGE, "--instance", "goose:235,217,67,64"],
        2,
        ["instances[0].object: 'goose' is not an object of model"],
    ),
    (
        ["predict", SAMPLE_IMAGE, "--instance", "duck:235,217,0,64", "--epsilon", "0"],
        2,
        [
            "epsilon: 0.0 is not a probability",
            "instances.0.bbox: bbox width and height must be at least 1 pixel",
        ],
    ),
    (
        ["predict", SAMPLE_IMAGE, "--instance", DUCK, "--nonconformity", "max"],
        2,
        ["argument --nonconformity: invalid choice: 'max'"],
    ),
    (["check-model", f"{NO_SUCH}model"], 3, [f"cannot be served: no manifest.json in {NO_SUCH}model"]),
    (["export-openapi", "--output", f"{NO_SUCH}openapi.json"], 1, [f"{NO_SUCH}openapi.json: No such file"]),
    (["manifest-schema", "--output", f"{NO_SUCH}schema.json"], 1, [f"{NO_SUCH}schema.json: No such file"]),
    (["serve", "--port", "eighty"], 2, ["argument --port: invalid int value: 'eighty'"]),
    (["frobnicate"], 2, ["argument COMMAND: invalid choice: 'frobnicate'", "(see keypoint-service --help)"]),
    ([], 2, ["the following arguments are required: COMMAND"]),
]


@pytest.fixture
def port_in_use() -> Iterator[int]:
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as sock:
        sock.bind(("127.0.0.1", 0))
        sock.listen()
        yield sock.getsockname()[1]


@pytest.fixture
def a_file(tmp_path: Path) -> Path:
    """A plain file: a data directory or output folder 'inside' it cannot be created (even by root)."""
    path = tmp_path / "a-file"
    path.write_text("not a folder\n")
    return path


def test_serve_refuses_a_port_in_use_before_loading_anything(tmp_path: Path, port_in_use: int) -> None:
    result = run(["serve"], tmp_path / "data", port=port_in_use)
    assert_one_line_error(result, 2, f"cannot listen on 127.0.0.1:{port_in_use}", "--port or CKS_PORT")
    assert not (tmp_path / "data").exists(), "serve prepared the data directory before finding the port taken"


@pytest.mark.parametrize(
    ("store_url", "fragment"),
    [
        ("mysql://x", "CKS_STORE_URL: use sqlite:///"),
        ("sqlite://host/x", "CKS_STORE_URL: sqlite URL 'sqlite://host/x' names a host"),
    ],
)
@pytest.mark.parametrize(
    "args", [["serve"], ["calibrate", SAMPLES], ["predict", SAMPLE_IMAGE, "--instance", DUCK]]
)
def test_a_bad_store_url_is_named(tmp_path: Path, args: list[str], store_url: str, fragment: str) -> None:
    result = run(args, tmp_path / "data", port=free_port(), store_url=store_url)
    assert_one_line_error(result, 2, "invalid settings", fragment)


def test_an_unreachable_postgresql_store_is_one_line_without_its_password(tmp_path: Path) -> None:
    url = f"postgresql://someone:s3cret@127.0.0.1:{free_port()}/kps"  # nothing listens there
    result = run(["calibrate", SAMPLES], tmp_path / "data", store_url=url)
    line = assert_one_line_error(result, 1, "the calibration store postgresql://someone@127.0.0.1:")
    assert "cannot connect to PostgreSQL" in line and "s3cret" not in line


@pytest.mark.parametrize(
    ("command", "settings", "fragments"),
    [
        ("serve", {"port": "abc"}, ["CKS_PORT: Input should be a valid integer"]),
        ("check-model", {"log_format": "xml"}, ["CKS_LOG_FORMAT: Input should be 'text' or 'json'"]),
        ("export-openapi", {"workers": "0", "log_level": "loud"}, ["CKS_WORKERS: ", "; CKS_LOG_LEVEL: "]),
    ],
)
def test_a_bad_setting_is_named(tmp_path: Path, command: str, settings: dict, fragments: list[str]) -> None:
    result = run([command], tmp_path / "data", **settings)
    assert_one_line_error(result, 2, "error: invalid settings: ", *fragments)


@pytest.mark.parametrize("args", [["serve"], ["predict", SAMPLE_IMAGE, "--instance", DUCK]])
def test_a_data_directory_that_cannot_be_created(tmp_path: Path, a_file: Path, args: list[str]) -> None:
    result = run(args, a_file / "data", port=free_port())
    assert_one_line_error(result, 1, f"{a_file / 'data'}: Not a directory")


@pytest.mark.parametrize(("args", "status", "fragments"), MISTAKES)
def test_a_mistake_is_one_line(tmp_path: Path, args: list[str], status: int, fragments: list[str]) -> None:
    assert_one_line_error(run(args, tmp_path / "data"), status, *fragments)


def test_the_server_reports_the_same_version(tmp_path: Path) -> None:
    with TestClient(create_app(Settings(data_dir=tmp_path / "served", inference_threads=1))) as client:
        response = client.get("/v1/model")
    assert response.status_code == 200, response.text
    printed = run(["--version"], tmp_path / "data").stdout.split()[-1]
    assert response.json()["service_version"] == printed == __version__


@pytest.mark.parametrize("command", list(EXAMPLES))
def test_every_command_has_help_with_examples(tmp_path: Path, command: str) -> None:
    result = run([command, "--help"], tmp_path / "data")
    assert result.returncode == 0 and result.stderr == "", result.stderr
    examples = result.stdout.split("examples:\n", 1)[1]
    assert f"keypoint-service {command}" in examples, result.stdout


def test_a_successful_one_shot_command_is_quiet_on_stderr(tmp_path: Path) -> None:
    result = run(["predict", SAMPLE_IMAGE, "--instance", DUCK], tmp_path / "data")
    assert result.returncode == 0, result.stderr
    assert result.stderr == "" and '"calibration"' in result.stdout


def test_serve_refuses_a_short_token_in_one_line(tmp_path: Path) -> None:
    tokens = tmp_path / "tokens"
    tokens.write_text("alice:short\n")
    result = run(["serve"], tmp_path / "data", admin_tokens_file=tokens, port=free_port())
    assert result.returncode == 2, result.stderr
    assert "line 1: the token of 'alice' must be at least 16 characters" in result.stderr
    assert "Traceback" not in result.stderr
    result = run(["serve"], tmp_path / "data", admin_token="change-me", port=free_port())
    assert result.returncode == 2, result.stderr
    assert result.stderr.splitlines() == [
        "error: CKS_ADMIN_TOKEN: the token must be at least 16 characters without spaces "
        "(make one with: openssl rand -hex 16)"
    ]
