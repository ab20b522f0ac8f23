"""Release hygiene: the license pyproject.toml states is the one in LICENSE, one version
(``service.__version__``) is what the package, the API and the changelog carry, and the wheel
holds the server (the training code runs from the repository)."""

from __future__ import annotations

import hashlib
import json
import re
import tomllib
from pathlib import Path

import pytest
from setuptools.config.pyprojecttoml import read_configuration

from service import __version__
from service.infra.settings import PACKAGE_ROOT
from tests.api.in_process import InProcess

PYPROJECT = PACKAGE_ROOT / "pyproject.toml"
# sha256 of https://www.apache.org/licenses/LICENSE-2.0.txt (also Debian's
# /usr/share/common-licenses/Apache-2.0): the full text, unchanged.
APACHE_2_0_SHA256 = "cfc7749b96f63bd31c3c42b5c471bf756814053e847c10f3eb003417bc523d30"


def test_license_file_is_the_apache_2_0_text_pyproject_states() -> None:
    project = tomllib.loads(PYPROJECT.read_text(encoding="utf-8"))["project"]
    assert project["license"] == {"text": "Apache-2.0"}
    assert hashlib.sha256((PACKAGE_ROOT / "LICENSE").read_bytes()).hexdigest() == APACHE_2_0_SHA256


@pytest.mark.filterwarnings("ignore:`\\[tool.setuptools.ext-modules\\]`")
def test_the_package_version_is_service_version() -> None:
    project = read_configuration(PYPROJECT, expand=True)["project"]
    assert project["version"] == __version__


@pytest.mark.filterwarnings("ignore:`\\[tool.setuptools.ext-modules\\]`")
def test_the_wheel_holds_the_server_not_the_training_code() -> None:
    packages = read_configuration(PYPROJECT, expand=True)["tool"]["setuptools"]["packages"]
    assert {
        "service",
        "service.infra",
        "service.serving",
        "service.api.predict",
        "calibration_store",
        "keypoint_client",
    } <= set(packages)
    assert not [name for name in packages if name.split(".")[0] in ("training", "tests", "benchmarks")]


def test_the_changelog_has_a_section_for_this_version() -> None:
    changelog = (PACKAGE_ROOT / "CHANGELOG.md").read_text(encoding="utf-8")
    assert re.search(rf"^## \[{re.escape(__version__)}\]", changelog, re.MULTILINE), (
        f"CHANGELOG.md has no '## [{__version__}]' section"
    )


def test_the_api_reports_the_version(tmp_path: Path) -> None:
    committed = json.loads((PACKAGE_ROOT / "openapi" / "openapi.json").read_text(encoding="utf-8"))
    assert committed["info"]["version"] == __version__
    with InProcess(tmp_path / "data") as server:
        assert server.client.get("/v1/model").json()["service_version"] == __version__
        assert server.client.get("/openapi.json").json()["info"]["version"] == __version__
