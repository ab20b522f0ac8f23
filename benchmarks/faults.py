"""Every fault of docs/operations.md, measured on real processes on loopback, one after the other.

    python -m benchmarks.faults          # the store outages, clients, images, shutdown, a full disk

Runs ``benchmarks.faults_store`` (a store outage under load: PostgreSQL stopped, then frozen,
then a SQLite store whose locks another process holds), ``benchmarks.faults_clients`` (slow
clients, a flood beside a polite client, huge images, zip bombs, SIGTERM) and
``benchmarks.faults_disk`` (a full disk, as root; identical uploads) with their defaults; each
prints its own figures. Run one alone for its options (``--help``).
"""

from __future__ import annotations

import sys

from benchmarks import faults_clients, faults_disk, faults_store


def main() -> int:
    status = 0
    for name, module, argv in (
        ("store outage", faults_store, []),
        ("frozen store", faults_store, ["--fault", "freeze"]),
        ("locked SQLite store", faults_store, ["--fault", "sqlite-locked"]),
        ("clients, images, shutdown", faults_clients, []),
        ("full disk, identical uploads", faults_disk, []),
    ):
        print(f"\n=== {name} ({module.__name__} {' '.join(argv)})", flush=True)
        status = max(status, module.main(argv) or 0)
    return status


if __name__ == "__main__":
    sys.exit(main())
