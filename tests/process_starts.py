"""Which test files start a process, and the few that may (issue 46: API behaviour in process, a
process only where the process is the point).

A pytest plugin, loaded by tests/conftest.py. It wraps the calls every process start goes through
(``subprocess``'s and ``multiprocessing``'s fork_exec, ``os.fork``, ``os.forkpty``,
``os.posix_spawn[p]``, ``os.system``) and charges a start to the fixture being set up or torn down,
else to the test running. A test file starts a process when one of its tests did, or used a fixture
that did. A test of a file not in ``ALLOWED`` that starts one fails at its teardown.

Not charged: the PostgreSQL server of the ``postgres_cluster`` fixture, started once per worker for
every file that stores in PostgreSQL (a real part, like the disk), and matplotlib's one listing of
the fonts for its cache.

``python -m pytest --process-starts=PATH`` writes ``{file: [what it started]}`` as JSON (each xdist
worker sends its part to the controller) and prints the count. A nested session (pytester) records
its starts, and so does the session around it.
"""

from __future__ import annotations

import _posixsubprocess
import json
import os
import subprocess
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import pytest

MAX_ALLOWED = 30
#: The files whose point is a process boundary, each with that boundary.
ALLOWED: dict[str, str] = {
    "tests/live/test_floods.py": "floods from many addresses, through HAProxy and straight to a server",
    "tests/live/test_decode_budget.py": "a server process's peak resident memory while it decodes",
    "tests/live/test_shutdown.py": "SIGTERM: a graceful stop, its exit status and bounds",
    "tests/live/test_jobs_stale.py": "SIGKILL of a server mid-job; another process takes it over",
    "tests/live/test_workers.py": "CKS_WORKERS=2: workers share metrics and drift; one SIGKILLed",
    "tests/live/test_replicas.py": "replica processes (host:pid) sharing jobs and drift windows",
    "tests/live/test_disk_full.py": "a real full tmpfs under a server; a worker SIGKILLed",
    "tests/live/test_store_outage.py": "PostgreSQL stopped and frozen; a process holding SQLite's locks",
    "tests/live/test_fleet.py": "three replicas behind HAProxy; one SIGKILLed, one drained",
    "tests/live/test_logs.py": "what a server process writes on stderr",
    "tests/live/test_readme_first_run.py": "the README's commands in bash with curl against `serve`",
    "tests/live/test_installed_commands.py": "the installed entry point and uvicorn, started as people do",
    "tests/live/test_schemathesis.py": "the schemathesis command line fuzzing a server",
    "tests/live/test_generated_client.py": "openapi-python-client generating a client",
    "tests/live/test_openapi_generator_client.py": "openapi-generator (Java) generating a client",
    "tests/live/test_typescript_clients.py": "TypeScript generators, tsc and node",
    "tests/live/client/test_isolation.py": "the client installed alone in a fresh virtual environment",
    "tests/deploy/test_api_pages.py": "Chromium driven by Playwright",
    "tests/deploy/test_console.py": "Chromium driven by Playwright; a server process's own metrics",
    "tests/deploy/test_container.py": "buildah building and running the image",
    "tests/deploy/test_ray_serve.py": "a local Ray cluster serving the service",
    "tests/unit/benchmarks/test_bench_ab_smoke.py": "a revision's export imported by its own interpreter",
    "tests/unit/benchmarks/test_bench_frames_smoke.py": "the benchmark's server processes",
    "tests/unit/benchmarks/test_bench_service_smoke.py": "raw onnxruntime sessions in processes",
    "tests/unit/test_client_models.py": "the model generator and ruff, as commands",
    "tests/unit/benchmarks/test_bench_peers_smoke.py": "the peers' servers and the int8 service",
    "tests/unit/calibration_store/test_processes.py": "several processes on one store; one SIGKILLed",
    "tests/unit/test_decoding_memory.py": "a fresh process's peak resident memory while it decodes",
    "tests/unit/test_process_starts.py": "sessions whose tests start processes, xdist's workers",
}
#: Fixtures whose processes serve every file that asks for them.
SHARED_FIXTURES = {"postgres_cluster"}
#: Programs a library starts once per machine, whatever the test.
INCIDENTAL = {"fc-list"}  # matplotlib's font cache

ACTIVE: list[Recorder] = []  # a session's, and a nested session's (pytester) within it


def _label(program: Any) -> str:
    return os.path.basename(os.fsdecode(program)) if program else "?"


def _wrap(call: Callable[..., Any], what: Callable[..., str]) -> Callable[..., Any]:
    def started(*args: Any, **kwargs: Any) -> Any:
        for recorder in ACTIVE:
            recorder.started(what(*args, **kwargs))
        return call(*args, **kwargs)

    started.__wrapped__ = call  # type: ignore[attr-defined]
    return started


def _install() -> None:
    """Wrap the process starts, once per interpreter (nested sessions share the wrappers)."""
    if hasattr(os.fork, "__wrapped__"):
        return
    fork_exec = _wrap(_posixsubprocess.fork_exec, lambda argv, *_: _label(argv[0] if argv else None))
    _posixsubprocess.fork_exec = fork_exec  # multiprocessing's spawn and forkserver
    subprocess._fork_exec = fork_exec  # type: ignore[attr-defined]  # bound at subprocess's import
    os.fork = _wrap(os.fork, lambda: "fork")
    os.forkpty = _wrap(os.forkpty, lambda: "forkpty")
    os.posix_spawn = _wrap(os.posix_spawn, lambda path, *_, **__: _label(path))
    os.posix_spawnp = _wrap(os.posix_spawnp, lambda path, *_, **__: _label(path))
    os.system = _wrap(os.system, lambda command: _label(command.split()[0] if command else None))


def _fixture_key(fixturedef: pytest.FixtureDef[Any]) -> str:
    return f"{fixturedef.baseid}::{fixturedef.argname}"


class Recorder:
    """One session's starts: per test (outside fixtures), per fixture, and per test file."""

    def __init__(self, config: pytest.Config) -> None:
        self.config = config
        self.within: list[str] = []  # the fixtures being set up or torn down, innermost last
        self.item: pytest.Item | None = None
        self.item_starts: set[str] = set()
        self.item_fixtures: set[tuple[str, str]] = set()
        self.fixture_starts: dict[str, set[str]] = {}
        self.files: dict[str, set[str]] = {}

    def started(self, what: str) -> None:
        if what in INCIDENTAL:
            return
        if self.within:
            self.fixture_starts.setdefault(self.within[-1], set()).add(what)
        elif self.item is not None:
            self.item_starts.add(what)

    @pytest.hookimpl(wrapper=True)
    def pytest_fixture_setup(self, fixturedef: pytest.FixtureDef[Any]) -> Iterator[object]:
        key = _fixture_key(fixturedef)
        # Its teardown, by these finalizers in reverse: enter, the fixture's own, leave.
        fixturedef.addfinalizer(self.within.pop)
        self.within.append(key)
        try:
            return (yield)
        finally:
            self.within.pop()
            fixturedef.addfinalizer(lambda: self.within.append(key))

    @pytest.hookimpl(wrapper=True)
    def pytest_runtest_protocol(self, item: pytest.Item) -> Iterator[object]:
        self.item, self.item_starts, self.item_fixtures = item, set(), set()
        try:
            return (yield)
        finally:
            self.item = None

    @pytest.hookimpl(wrapper=True)
    def pytest_runtest_makereport(self, item: pytest.Item, call: pytest.CallInfo[None]) -> Iterator[Any]:
        report = yield
        # The fixtures this test used, those asked for by getfixturevalue too.
        used = item._request._fixture_defs.values()  # type: ignore[attr-defined]
        self.item_fixtures.update((_fixture_key(d), d.argname) for d in used)
        if call.when == "teardown":
            self._charge(item, report)
        return report

    def _charge(self, item: pytest.Item, report: pytest.TestReport) -> None:
        fixtures = {
            f"fixture {name}"
            for key, name in self.item_fixtures
            if key in self.fixture_starts and name not in SHARED_FIXTURES
        }
        starts = self.item_starts | fixtures
        if not starts:
            return
        file = item.nodeid.split("::")[0]
        self.files.setdefault(file, set()).update(starts)
        if file not in ALLOWED and report.passed:
            report.outcome = "failed"
            report.longrepr = (
                f"{file} started a process ({', '.join(sorted(starts))}) and is not in ALLOWED"
                " (tests/process_starts.py): call the service in process (tests/api/in_process.py)"
                " unless a process boundary is the point"
            )

    def as_json(self) -> dict[str, list[str]]:
        return {file: sorted(starts) for file, starts in sorted(self.files.items())}

    @pytest.hookimpl(optionalhook=True)
    def pytest_testnodedown(self, node: Any, error: object) -> None:
        for file, starts in node.workeroutput.get("process_starts", {}).items():
            self.files.setdefault(file, set()).update(starts)

    def pytest_sessionfinish(self) -> None:
        if hasattr(self.config, "workeroutput"):  # an xdist worker: the controller writes
            self.config.workeroutput["process_starts"] = self.as_json()
        elif path := self.config.getoption("process_starts"):
            Path(path).write_text(json.dumps(self.as_json(), indent=1) + "\n")

    def pytest_terminal_summary(self, terminalreporter: Any) -> None:
        if self.config.getoption("process_starts") and not hasattr(self.config, "workeroutput"):
            files = self.as_json()
            terminalreporter.write_sep("-", f"{len(files)} test files started a process")
            for file, starts in files.items():
                terminalreporter.write_line(f"{file}: {', '.join(starts)}")


def pytest_addoption(parser: pytest.Parser) -> None:
    parser.addoption(
        "--process-starts",
        metavar="PATH",
        help="write the test files that started a process (and what) to PATH as JSON; print them",
    )


def pytest_configure(config: pytest.Config) -> None:
    _install()
    recorder = Recorder(config)
    ACTIVE.append(recorder)
    config.pluginmanager.register(recorder, "process-starts-recorder")


def pytest_unconfigure(config: pytest.Config) -> None:
    recorder = config.pluginmanager.get_plugin("process-starts-recorder")
    if recorder in ACTIVE:
        ACTIVE.remove(recorder)
