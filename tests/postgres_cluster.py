"""A throwaway PostgreSQL cluster for tests, started from the machine's server binaries.

initdb into a temporary directory, pg_ctl start on a free loopback port (unix socket in
the same directory), databases created on demand, stop and remove at the end: the way
pytest-postgresql does it. When running as root (initdb refuses root), the cluster runs
as the `postgres` system user on a directory chowned to it.

Use from any test folder through the fixtures of tests/conftest.py (`postgres_url`,
`postgres_cluster`), or directly:

    with PostgresCluster.start() as cluster:
        url = cluster.create_database()
        cluster.stop_server()   # an outage: the data and the port are kept
        cluster.start_server()
        cluster.freeze_server() # SIGSTOP: neither refuses nor answers
        cluster.thaw_server()
"""

from __future__ import annotations

import contextlib
import glob
import os
import pwd
import shutil
import signal
import socket
import subprocess
import tempfile
import uuid
from pathlib import Path
from types import TracebackType

SEARCH_DIRS = (
    "/usr/lib/postgresql/*/bin",
    "/usr/local/pgsql/bin",
    "/opt/homebrew/opt/postgresql*/bin",
)
INSTALL_HINT = (
    "PostgreSQL server binaries (initdb, pg_ctl) not found on PATH or in /usr/lib/postgresql/*/bin;"
    " install them (Debian/Ubuntu: apt-get install postgresql) or set PG_BINDIR"
)


class PostgresClusterError(RuntimeError):
    """The throwaway cluster could not be created or started."""


def find_bindir() -> Path:
    """Directory holding initdb and pg_ctl: $PG_BINDIR, PATH, then usual install dirs."""
    explicit = os.environ.get("PG_BINDIR")
    candidates = [explicit] if explicit else []
    on_path = shutil.which("initdb")
    if on_path:
        candidates.append(str(Path(on_path).resolve().parent))
    for pattern in SEARCH_DIRS:
        candidates.extend(sorted(glob.glob(pattern), reverse=True))
    for candidate in candidates:
        path = Path(candidate)
        if (path / "initdb").is_file() and (path / "pg_ctl").is_file():
            return path
    raise PostgresClusterError(INSTALL_HINT)


def free_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as sock:
        sock.bind(("127.0.0.1", 0))
        return int(sock.getsockname()[1])


def _run_as() -> tuple[list[str], pwd.struct_passwd | None]:
    """Command prefix and account to run the server as (postgres when we are root)."""
    if os.geteuid() != 0:
        return [], None
    try:
        account = pwd.getpwnam("postgres")
    except KeyError as exc:
        raise PostgresClusterError(
            "running as root: initdb refuses root and there is no 'postgres' user;"
            " create one (useradd --system postgres) or run the tests as a normal user"
        ) from exc
    runuser = shutil.which("runuser")
    if runuser:
        return [runuser, "-u", "postgres", "--"], account
    return ["setpriv", f"--reuid={account.pw_uid}", f"--regid={account.pw_gid}", "--init-groups"], account


def _children(parent: int) -> list[int]:
    children = []
    for stat in Path("/proc").glob("[0-9]*/stat"):
        try:
            if int(stat.read_text().rpartition(")")[2].split()[1]) == parent:
                children.append(int(stat.parent.name))
        except (OSError, ValueError, IndexError):  # it exited meanwhile
            continue
    return children


class PostgresCluster:
    """A running throwaway cluster; `create_database()` returns a URL per database."""

    def __init__(self, bindir: Path, base: Path, port: int, prefix: list[str]) -> None:
        self.bindir = bindir
        self.base = base
        self.datadir = base / "data"
        self.socket_dir = base / "socket"
        self.port = port
        self._prefix = prefix
        self.user = "postgres"

    @classmethod
    def start(cls, attempts: int = 3) -> PostgresCluster:
        """initdb + pg_ctl start; retries on another free port if the port was taken."""
        bindir = find_bindir()
        prefix, account = _run_as()
        # as root the server runs as postgres, which must reach the directory: use /tmp
        base = Path(tempfile.mkdtemp(prefix="pgtest-", dir="/tmp" if account else None))
        try:
            cluster = cls(bindir, base, free_port(), prefix)
            cluster._initdb(account)
            for attempt in range(attempts):
                if cluster._pg_ctl_start(last=attempt == attempts - 1):
                    return cluster
                cluster.port = free_port()
        except BaseException:
            shutil.rmtree(base, ignore_errors=True)
            raise
        raise AssertionError("unreachable")

    def _run(self, args: list[str], what: str) -> subprocess.CompletedProcess[str]:
        result = subprocess.run(
            [*self._prefix, *args], capture_output=True, text=True, timeout=120, check=False
        )
        if result.returncode != 0:
            raise PostgresClusterError(f"{what} failed ({result.returncode}): {result.stderr}")
        return result

    def _initdb(self, account: pwd.struct_passwd | None) -> None:
        self.socket_dir.mkdir()
        if account is not None:
            for path in (self.base, self.socket_dir):
                os.chown(path, account.pw_uid, account.pw_gid)
        self._run(
            [
                str(self.bindir / "initdb"),
                "-D",
                str(self.datadir),
                "-U",
                self.user,
                "--auth=trust",
                "--encoding=UTF8",
                "--locale=C",
                "--no-sync",
            ],
            "initdb",
        )

    def _pg_ctl_start(self, last: bool) -> bool:
        options = (
            f"-p {self.port} -k {self.socket_dir} -c listen_addresses=127.0.0.1"
            " -c fsync=off -c synchronous_commit=off -c full_page_writes=off"
            " -c max_connections=200 -c shared_buffers=64MB"
        )
        try:
            self._run(
                [
                    str(self.bindir / "pg_ctl"),
                    "start",
                    "-w",
                    "-t",
                    "60",
                    "-D",
                    str(self.datadir),
                    "-l",
                    str(self.base / "server.log"),
                    "-o",
                    options,
                ],
                "pg_ctl start",
            )
        except PostgresClusterError as exc:
            if last:
                raise PostgresClusterError(f"{exc}\nserver log:\n{self.server_log()}") from exc
            return False
        return True

    def stop_server(self) -> None:
        """Stop the server as an outage would (fast mode: clients are cut off), keeping its data
        and port for ``start_server``."""
        self._run(
            [str(self.bindir / "pg_ctl"), "stop", "-m", "fast", "-w", "-t", "60", "-D", str(self.datadir)],
            "pg_ctl stop",
        )

    def start_server(self) -> None:
        """Start the server stopped by ``stop_server`` again, on the same port."""
        self._pg_ctl_start(last=True)

    def freeze_server(self) -> None:
        """SIGSTOP the server and its backends: a database that neither refuses nor answers
        (a paused VM). ``thaw_server`` lets it go on."""
        self._signal_server(signal.SIGSTOP)

    def thaw_server(self) -> None:
        self._signal_server(signal.SIGCONT)

    def _signal_server(self, signum: int) -> None:
        postmaster = int((self.datadir / "postmaster.pid").read_text().split()[0])
        for pid in [postmaster, *_children(postmaster)]:
            with contextlib.suppress(ProcessLookupError):
                os.kill(pid, signum)

    def server_log(self) -> str:
        try:
            return (self.base / "server.log").read_text(errors="replace")[-4000:]
        except OSError:
            return ""

    def url(self, database: str = "postgres") -> str:
        return f"postgresql://{self.user}@127.0.0.1:{self.port}/{database}"

    def _admin(self, sql: str) -> None:
        import psycopg

        with psycopg.connect(self.url(), autocommit=True, connect_timeout=30) as conn:
            conn.execute(sql)

    def create_database(self, name: str | None = None) -> str:
        """Create an empty database and return its URL."""
        name = name or f"test_{uuid.uuid4().hex[:12]}"
        self._admin(f'CREATE DATABASE "{name}"')
        return self.url(name)

    def drop_database(self, name: str) -> None:
        """Drop a database, disconnecting its remaining clients."""
        self._admin(f'DROP DATABASE IF EXISTS "{name}" WITH (FORCE)')

    def stop(self) -> None:
        """Stop the server (immediate mode) and delete its directory."""
        try:
            subprocess.run(
                [
                    *self._prefix,
                    str(self.bindir / "pg_ctl"),
                    "stop",
                    "-m",
                    "immediate",
                    "-w",
                    "-D",
                    str(self.datadir),
                ],
                capture_output=True,
                timeout=60,
                check=False,
            )
        finally:
            shutil.rmtree(self.base, ignore_errors=True)

    def __enter__(self) -> PostgresCluster:
        return self

    def __exit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        self.stop()
