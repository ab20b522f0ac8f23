"""A validated COCO batch made ready for scoring: repeats found (refused or dropped) and
instances rejected by the box rule counted against the share the caller allows.

Both run before anything is scored (before an upload's 202): a batch that would be
refused never becomes a job.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, replace

from calibration_store import ScoreTable, VersionInfo
from service.calibration.coco import NamedBatch, Rejection
from service.calibration.fingerprints import Fingerprint, find_repeats, fingerprints
from service.errors import Conflict, InvalidInput

#: how many repeats or rejections a refusal lists (the count is always given)
LISTED = 20
REJECTED_SHARE_SETTING = "CKS_MAX_REJECTED_SHARE"


@dataclass(frozen=True)
class PreparedBatch:
    """A batch to score: its instances (repeats dropped), their fingerprints, what was left out."""

    named: NamedBatch
    fingerprints: tuple[Fingerprint, ...]
    repeats_dropped: int
    rejected: tuple[Rejection, ...]

    @property
    def annotations(self) -> int:
        """Annotations the batch held before anything was left out."""
        return self.named.batch.annotations + self.repeats_dropped


def prepare_batch(
    named: NamedBatch,
    parent: VersionInfo | None,
    parent_table: ScoreTable | None,
    *,
    dedupe: bool,
    max_rejected_share: float,
) -> PreparedBatch:
    """Refuse repeats (409, unless ``dedupe`` drops them) and too many rejected instances (422)."""
    batch = named.batch
    prints = fingerprints(batch)
    sources = parent.source_batches if parent else ()
    number = parent.number if parent else None
    repeats = find_repeats(batch, prints, named.sha256, parent_table, sources, number)
    if repeats and not dedupe:
        raise _repeats_refused(repeats, batch.count)
    repeated = {(r.image_id, r.annotation_id) for r in repeats}
    kept = [(i, p) for i, p in zip(batch.instances, prints, strict=True)
            if (i.image_id, i.annotation_id) not in repeated]  # fmt: skip
    check_rejected_share(batch.rejected, batch.annotations, max_rejected_share)
    if not kept:
        raise InvalidInput("no instance of the batch is left to calibrate with once repeats are dropped")
    instances = tuple(i for i, _ in kept)
    return PreparedBatch(
        named=replace(named, batch=replace(batch, instances=instances)),
        fingerprints=tuple(p for _, p in kept),
        repeats_dropped=len(repeats),
        rejected=batch.rejected,
    )


def check_rejected_share(rejected: Sequence[Rejection], total: int, max_share: float) -> None:
    """422 listing the rejections when more than ``max_share`` of ``total`` instances were rejected."""
    if not rejected or len(rejected) <= max_share * total:
        return
    listed = [r.describe() for r in rejected[:LISTED]]
    if len(rejected) > LISTED:
        listed.append(f"... and {len(rejected) - LISTED} more")
    raise InvalidInput(
        f"{len(rejected)} of {total} instances were rejected (first: {listed[0]}), more than the allowed"
        f" share of {max_share:g} (max_rejected_share, default {REJECTED_SHARE_SETTING}); fix them, or"
        " allow a larger share to calibrate without them",
        errors=listed,
        extensions={"rejected": len(rejected), "instances": total},
    )


def _repeats_refused(repeats: list[Rejection], count: int) -> Conflict:
    listed = [r.describe() for r in repeats[:LISTED]]
    if len(repeats) > LISTED:
        listed.append(f"... and {len(repeats) - LISTED} more")
    return Conflict(
        f"{len(repeats)} of {count} instances are already counted (first: {listed[0]}): each instance"
        " may enter a calibration once. Remove them, or drop them with dedupe=true (CLI: --dedupe)",
        errors=listed,
        extensions={"duplicates": len(repeats)},
    )
