"""At most 30 test files start a process, each for a process boundary that is its point
(tests/process_starts.py): a test of any other file that starts one fails, and
``--process-starts`` lists the files that did, from xdist's workers too. The sessions checked here
run in this process (pytester)."""

from __future__ import annotations

import json

import pytest

from service.infra.settings import PACKAGE_ROOT
from tests.process_starts import ALLOWED, MAX_ALLOWED

STARTER = """
import subprocess

import pytest


@pytest.fixture(scope="module")
def started():
    subprocess.run(["true"], check=True)


@pytest.fixture(scope="session")
def postgres_cluster():  # as tests/conftest.py's: a server shared by every file that asks
    subprocess.run(["true"], check=True)


def test_starts_one():
    subprocess.run(["true"], check=True)


def test_uses_a_fixture_that_did(started):
    pass


def test_a_shared_server_is_not_charged(postgres_cluster):
    pass
"""


def test_the_allowed_files_are_few_existing_and_each_says_why() -> None:
    assert len(ALLOWED) <= MAX_ALLOWED, f"{len(ALLOWED)} files may start a process, at most {MAX_ALLOWED}"
    for file, reason in ALLOWED.items():
        assert (PACKAGE_ROOT / file).is_file(), f"{file} is allowed but does not exist"
        assert reason.strip() and "\n" not in reason, f"{file}: say in one line which boundary is its point"


def run_session(pytester: pytest.Pytester, *args: str) -> pytest.RunResult:
    pytester.makepyfile(test_starter=STARTER, test_quiet="def test_quiet():\n    pass\n")
    plugins = ["-p", "tests.process_starts", "-p", "no:cacheprovider", "-p", "no:benchmark"]
    return pytester.runpytest_inprocess(*plugins, *args)


def test_a_file_not_allowed_that_starts_a_process_fails(pytester: pytest.Pytester) -> None:
    result = run_session(pytester)
    result.assert_outcomes(passed=4, errors=2)
    result.stdout.fnmatch_lines(["*test_starter.py started a process (true) and is not in ALLOWED*"])
    result.stdout.fnmatch_lines(["*test_starter.py started a process (fixture started) and is not*"])


def test_an_allowed_file_passes_and_the_starts_are_listed(
    pytester: pytest.Pytester, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.setitem(ALLOWED, "test_starter.py", "starts true")
    listed = pytester.path / "starts.json"
    result = run_session(pytester, f"--process-starts={listed}")
    result.assert_outcomes(passed=4)
    assert json.loads(listed.read_text()) == {"test_starter.py": ["fixture started", "true"]}
    result.stdout.fnmatch_lines(
        ["*1 test files started a process*", "test_starter.py: fixture started, true"]
    )


def test_an_xdist_worker_reports_to_the_controller(pytester: pytest.Pytester) -> None:
    listed = pytester.path / "starts.json"
    result = run_session(pytester, "-n", "1", f"--process-starts={listed}")
    result.assert_outcomes(passed=4, errors=2)  # the worker checks too
    assert json.loads(listed.read_text()) == {"test_starter.py": ["fixture started", "true"]}
