"""The audit trail: every administrative action, who did it, from where and why.

Entries go to the calibration store's append-only audit table (nothing in the API can
change them) and to the log as one line each (``audit action=... outcome=... who=...``; in
JSON those are members of the line). An entry about a stored change is written
in the same transaction as the change; a refusal is appended on its own.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from typing import Any

from calibration_store import CalibrationStore, NewAuditEntry, StoreError
from service.runtime.logs import log_fields

log = logging.getLogger("service.audit")  # a stable name: operators route and filter these lines by it


@dataclass(frozen=True)
class Operator:
    """Who acts: the name of the admin token used (or a CLI user) and the client address."""

    name: str
    client: str = ""


class AuditTrail:
    """Builds, stores and logs the audit entries of one model."""

    def __init__(self, store: CalibrationStore, model_hash: str) -> None:
        self._store = store
        self._model_hash = model_hash

    def entry(
        self,
        operator: Operator,
        action: str,
        outcome: str,
        *,
        version: int | None = None,
        previous_version: int | None = None,
        reason: str = "",
        details: dict[str, Any] | None = None,
    ) -> NewAuditEntry:
        return NewAuditEntry(
            model_hash=self._model_hash,
            who=operator.name,
            action=action,
            outcome=outcome,
            version=version,
            previous_version=previous_version,
            reason=reason,
            client=operator.client,
            details=details or {},
        )

    def record(self, operator: Operator, action: str, outcome: str, **fields: Any) -> None:
        """Append one entry on its own (refusals, uploads); a store failure is logged, not raised."""
        entry = self.entry(operator, action, outcome, **fields)
        try:
            self._store.append_audit(entry)
        except StoreError as error:
            fields = {**audit_fields(entry), "error": str(error)}
            log_fields(log, "audit entry not stored", fields, logging.ERROR)
            return
        written(entry)


def written(*entries: NewAuditEntry) -> None:
    """Log entries that reached the store."""
    for entry in entries:
        log_fields(log, "audit", audit_fields(entry))


def audit_fields(entry: NewAuditEntry) -> dict[str, Any]:
    """The fields of an entry's log line: who did what, with what outcome, from where, why."""
    return {
        "action": entry.action,
        "outcome": entry.outcome,
        "who": entry.who,
        "client": entry.client,
        "version": entry.version,
        "previous_version": entry.previous_version,
        "reason": entry.reason,
        "details": dict(entry.details) or None,
    }
