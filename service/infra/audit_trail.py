"""The audit trail: every administrative action, who did it, from where and why.

Entries go to the store's append-only audit table and to the log. An entry about a stored change is
written in the change's transaction; one the store cannot take now is logged at once, kept in this
process's outbox file (adopted by the next process of this host to start) and appended once it can.
"""

from __future__ import annotations

import json
import logging
import os
import socket
import threading
import time
from dataclasses import asdict, dataclass, replace
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

from calibration_store import CalibrationStore, NewAuditEntry, StoreError
from service.infra.logs import log_fields
from service.infra.processes import process_folder, process_running

log = logging.getLogger("service.audit")  # a stable name: operators route and filter these lines by it
#: how often entries the store could not take are tried again
RETRY_S = 1.0


@dataclass(frozen=True)
class Operator:
    """Who acts: the name of the admin token used (or a CLI user) and the client address."""

    name: str
    client: str = ""


class AuditTrail:
    """Builds, stores and logs the audit entries of one model."""

    def __init__(self, store: CalibrationStore, model_hash: str, outbox: Path | None = None) -> None:
        self._store = store
        self._model_hash = model_hash
        self._pending: list[NewAuditEntry] = []  # oldest first
        self._lock = threading.Lock()
        self._outbox = None if outbox is None else outbox / f"{process_folder(outbox).name}.jsonl"
        if outbox is not None:
            self._adopt(outbox)

    def entry(self, operator: Operator, action: str, outcome: str, **fields: Any) -> NewAuditEntry:
        """``fields``: NewAuditEntry's version, previous_version, reason and details."""
        fields["details"] = fields.get("details") or {}
        return NewAuditEntry(
            self._model_hash, operator.name, action, outcome, client=operator.client, **fields
        )

    def record(self, operator: Operator, action: str, outcome: str, **fields: Any) -> None:
        """Append one entry on its own; one the store cannot take now is logged and appended later."""
        entry = self.entry(operator, action, outcome, **fields)
        try:
            self._store.append_audit(entry)
        except StoreError as error:
            self._defer(entry, error)
            return
        written(entry)

    def record_later(self, operator: Operator, action: str, outcome: str, **fields: Any) -> None:
        """Log an entry now and append it from a thread retrying every RETRY_S: for refusals the store
        caused, which waiting on it again would only delay."""
        self._defer(self.entry(operator, action, outcome, **fields), None)

    def _defer(self, entry: NewAuditEntry, error: StoreError | None) -> None:
        happened = datetime.now(UTC).isoformat()
        entry = replace(entry, details={**entry.details, "happened_at": happened})
        fields = {**audit_fields(entry), "error": None if error is None else str(error)}
        log_fields(log, "audit entry not stored yet", fields, logging.WARNING)
        self._enqueue([entry])

    def _enqueue(self, entries: list[NewAuditEntry]) -> None:
        if not entries:
            return
        with self._lock:
            self._pending.extend(entries)
            self._keep_outbox()
            if len(self._pending) == len(entries):
                threading.Thread(target=self._append_pending, name="audit-retry", daemon=True).start()

    def _append_pending(self) -> None:
        while True:
            with self._lock:
                if not self._pending:
                    return
                entry = self._pending[0]
            try:
                self._store.append_audit(entry)
            except StoreError:
                time.sleep(RETRY_S)
                continue
            written(entry)
            with self._lock:
                self._pending.pop(0)
                self._keep_outbox()

    def _keep_outbox(self) -> None:
        """Write the waiting entries to this process's outbox (the lock is held; removed when none wait)."""
        if self._outbox is None:
            return
        try:
            if not self._pending:
                self._outbox.unlink(missing_ok=True)
                return
            self._outbox.parent.mkdir(parents=True, exist_ok=True)
            draft = self._outbox.with_name(f".{self._outbox.name}")
            with open(draft, "w", encoding="utf-8") as out:
                out.writelines(json.dumps(asdict(entry), default=str) + "\n" for entry in self._pending)
                out.flush()
                os.fsync(out.fileno())
            draft.replace(self._outbox)
        except OSError as error:
            log.warning(
                f"audit outbox {self._outbox} not written ({error}):"
                f" {len(self._pending)} entries wait in memory only"
            )

    def _adopt(self, folder: Path) -> None:
        """Take over the outboxes of stopped processes of this host (a rename: one adopter each), that
        of this process's name included (a restarted container's server is pid 1 again)."""
        for path in sorted(folder.glob(f"{socket.gethostname()}--*.jsonl")) if folder.is_dir() else []:
            pid = path.stem.rpartition("--")[2]
            if path != self._outbox and (not pid.isdigit() or process_running(int(pid))):
                continue
            claimed = path.with_name(f".adopted-{path.name}")
            try:
                path.rename(claimed)
            except FileNotFoundError:  # another process adopted it first
                continue
            lines = claimed.read_text(encoding="utf-8").splitlines()
            entries = [NewAuditEntry(**json.loads(line)) for line in lines if line.strip()]
            log.info("audit: %d entries of stopped process %s wait for the store", len(entries), pid)
            self._enqueue(entries)  # in this process's outbox before the adopted one goes
            claimed.unlink()


def written(*entries: NewAuditEntry) -> None:
    """Log entries that reached the store."""
    for entry in entries:
        log_fields(log, "audit", audit_fields(entry))


def audit_fields(entry: NewAuditEntry) -> dict[str, Any]:
    """The fields of an entry's log line: who did what, with what outcome, from where, why."""
    names = ("action", "outcome", "who", "client", "version", "previous_version", "reason")
    return {name: getattr(entry, name) for name in names} | {"details": dict(entry.details) or None}
