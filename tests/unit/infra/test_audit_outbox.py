"""The audit outbox on a real SQLite store: entries a stopped process left waiting for the store
are appended by the next process of its host, even when that process has the same pid (a
restarted container's server is pid 1 again)."""

from __future__ import annotations

import json
from dataclasses import asdict
from pathlib import Path

from calibration_store import NewAuditEntry, open_store
from service.infra.audit_trail import AuditTrail
from service.infra.processes import process_folder
from tests.service_calls import BUSY_MACHINE_MARGIN_S, wait_until

MODEL = "audit-outbox-model"


def _left_waiting(outbox: Path, pid: int | None, reason: str) -> Path:
    """An outbox file of this host's process ``pid`` (default: this one's) with one entry."""
    path = outbox / f"{process_folder(outbox, pid).name}.jsonl"
    outbox.mkdir(parents=True, exist_ok=True)
    entry = NewAuditEntry(model_hash=MODEL, who="admin", action="admin", outcome="refused", reason=reason)
    path.write_text(json.dumps(asdict(entry)) + "\n", encoding="utf-8")
    return path


def test_the_outbox_of_a_process_with_this_pid_is_appended_not_replaced(tmp_path: Path) -> None:
    outbox = tmp_path / "audit-outbox"
    own = _left_waiting(outbox, None, "left by the previous process with this pid")
    with open_store(f"sqlite://{tmp_path}/calibration.db") as store:
        AuditTrail(store, MODEL, outbox)

        def reasons() -> list[str]:
            return [entry.reason for entry in store.audit_log(MODEL)]

        wait_until(
            lambda: reasons() == ["left by the previous process with this pid"],
            "appended",
            timeout=2 + BUSY_MACHINE_MARGIN_S,
        )
        wait_until(lambda: not own.exists(), "the outbox emptied", timeout=2 + BUSY_MACHINE_MARGIN_S)


def test_the_outbox_of_a_running_process_is_left_to_it(tmp_path: Path) -> None:
    outbox = tmp_path / "audit-outbox"
    running = _left_waiting(outbox, 1, "pid 1 runs: its entries are its own to append")
    with open_store(f"sqlite://{tmp_path}/calibration.db") as store:
        AuditTrail(store, MODEL, outbox)
        assert running.exists() and store.audit_log(MODEL) == []
