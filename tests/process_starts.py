"""Which test files start a process, and the few that may (issue 46: API behaviour in process).

A pytest plugin (loaded by tests/conftest.py). It wraps the calls every process start goes through
(``subprocess``'s and ``multiprocessing``'s fork_exec, ``os.fork``, ``os.forkpty``,
``os.posix_spawn[p]``, ``os.system``) and charges a start to the fixture being set up or torn down,
else to the test running. A test file starts a process when one of its tests did or uses a fixture
that did. A test of a file not in ``ALLOWED`` that starts one fails at its teardown.

``--process-starts=PATH`` writes ``{file: [what started]}`` as JSON (each xdist worker sends its
part to the controller) and prints the count. A nested session (pytester) records its own starts.
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

# The files whose point is a process boundary, each with that boundary (at most 30).
ALLOWED: dict[str, str] = {}
MAX_ALLOWED = 30

ACTIVE: list[Recorder] = []  # the innermost session's recorder gets the starts


def _label(program: Any) -> str:
    return os.path.basename(os.fsdecode(program)) if program else "?"


def _wrap(call: Callable[..., Any], what: Callable[..., str]) -> Callable[..., Any]:
    def started(*args: Any, **kwargs: Any) -> Any:
        if ACTIVE:
            ACTIVE[-1].started(what(*args, **kwargs))
            if os.environ.get("REFUSE_STARTS") and (ACTIVE[-1].item or ACTIVE[-1].within):  # TEMPORARY survey aid
                raise RuntimeError("refused")
        return call(*args, **kwargs)

    started.__wrapped__ = call  # type: ignore[attr-defined]
    return started


def _install() -> None:
    """Wrap the process starts once per interpreter (nested sessions share the wrappers)."""
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
    return f"{fixturedef.baseid}::{fixturedef.argname}" if fixturedef.baseid else fixturedef.argname


class Recorder:
    """One session's starts: per test file directly, per fixture, and the fixtures each file used."""

    def __init__(self, config: pytest.Config) -> None:
        self.config = config
        self.within: list[str] = []  # the fixtures being set up or torn down, innermost last
        self.item: pytest.Item | None = None
        self.item_starts: set[str] = set()
        self.item_fixtures: set[tuple[str, str]] = set()
        self.fixture_starts: dict[str, set[str]] = {}
        self.files: dict[str, set[str]] = {}  # file -> what its tests started, fixtures by name

    def started(self, what: str) -> None:
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
        fixtures = {f"fixture {name}" for key, name in self.item_fixtures if key in self.fixture_starts}
        starts = self.item_starts | fixtures
        if not starts:
            return
        file = item.nodeid.split("::")[0]
        self.files.setdefault(file, set()).update(starts)
        if file not in ALLOWED and report.passed:
            report.outcome = "failed"
            report.longrepr = (
                f"{file} started a process ({', '.join(sorted(starts))}) and is not in"
                " tests/process_starts.py ALLOWED: call the API in process (tests/api/in_process.py)"
                " unless a process boundary is the point"
            )

    def merge(self, files: dict[str, list[str]]) -> None:
        for file, starts in files.items():
            self.files.setdefault(file, set()).update(starts)

    def as_json(self) -> dict[str, list[str]]:
        return {file: sorted(starts) for file, starts in sorted(self.files.items())}

    @pytest.hookimpl(optionalhook=True)
    def pytest_testnodedown(self, node: Any, error: object) -> None:
        self.merge(node.workeroutput.get("process_starts", {}))

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
        help="write the test files that started a process (and what) to PATH as JSON; print the count",
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
