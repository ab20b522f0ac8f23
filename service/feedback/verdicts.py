"""The verdicts of a label: what live coverage counts of a labelled prediction, judged once.

A label's judgement never changes once made, so the feedback use case judges it when it stores
the label and keeps the result beside it (calib_verdicts, about 2 KB where the retained record is
11 KB of heatmap statistics): live coverage then reads these, never the records (docs/feedback.md,
"what a read costs"). ``verdicts`` splits the prediction into its judged units (each labelled
keypoint, or with ``coverage: object`` each instance whose keypoints were all labelled: covered
when every one of them is in its set) and gathers them into the groups live coverage counts (the
version as a whole, per object, keypoint, camera stream, caller group and Mondrian stratum).

What varies from label to label is little: how many units of each group were covered, and the
look (its tally). The rest, the shape (version, guarantee, query, the groups, and per group the
floor of each unit in unit order), repeats over the frames of a stream; it is kept as one JSON
text in a column of its own, so that a reader parses each shape once and counts a label as a
list of numbers. A floor is kept as
the calibration guarantees (n, t, epsilon, delta) behind it, not as a number: the number depends
on CKS_FEEDBACK_ALARM_LEVEL, which the reader applies.
"""

from __future__ import annotations

import json
from collections.abc import Iterator, Sequence
from dataclasses import dataclass
from typing import Any

from calibration_store import LabelVerdicts, RetainedPrediction


@dataclass(frozen=True)
class Unit:
    """One judged keypoint (or instance, object scope) of a labelled prediction."""

    object: str
    keypoint: str | None
    stream: str
    group: str | None
    stratum: str | None  # the Mondrian stratum whose threshold served it (None: not stratified)
    covered: bool
    guarantees: tuple[tuple[Any, ...], ...]  # (n, t, epsilon, delta) of its rows: its floor is the least


def verdicts(prediction: RetainedPrediction, keypoint_names: list[str]) -> LabelVerdicts:
    """The compact judgement of a labelled prediction that live coverage folds (module doc): its
    shape (JSON text), and as its tally its ``look`` and ``covered``, the covered units of each of
    the shape's groups."""
    record = prediction.record
    query = record["query"]
    floors: dict[tuple, int] = {}
    groups: dict[tuple[str, str], tuple[list[int], list[list[int]]]] = {}
    for unit in units(record, (prediction.labels or {}).get("rows", []), keypoint_names, prediction.stream):
        floor = floors.setdefault(unit.guarantees, len(floors))
        for name in group_names(unit):
            covered, runs = groups.setdefault(name, ([0], []))
            covered[0] += unit.covered
            if runs and runs[-1][0] == floor:
                runs[-1][1] += 1
            else:
                runs.append([floor, 1])  # [floor, units in a row with it]
    shape = {
        "version": prediction.version,
        "guarantee": "exchangeable" if record.get("adaptive") is None else "adaptive",
        "query": [query["nonconformity"], query["coverage"], query["epsilon"], query["delta"]],
        "floors": [[list(g) for g in guarantees] for guarantees in floors],
        "groups": [[level, name, runs] for (level, name), (_, runs) in groups.items()],
    }
    tally = {
        "look": record.get("look", prediction.id),  # rows kept before looks: one look each
        "covered": [covered[0] for covered, _ in groups.values()],
    }
    return LabelVerdicts(json.dumps(shape, separators=(",", ":")), tally)


def units(
    record: dict[str, Any], judged_rows: Sequence[dict[str, Any]], keypoint_names: list[str], stream: str
) -> Iterator[Unit]:
    """The judged units of one labelled prediction (keypoints, or whole instances: object scope)."""
    rows, instances = record["rows"], record["instances"]
    for index, row, covered in covered_units(record, judged_rows):
        members = [r for r, kept in enumerate(rows) if kept["instance"] == index] if row is None else [row]
        guarantees = tuple(dict.fromkeys(_guarantee(rows[r]["guarantee"]) for r in members))
        name = None if row is None else keypoint_names[rows[row]["channel"]]
        strata = {rows[r].get("stratum") for r in members}  # one per instance with coverage object
        stratum = strata.pop() if len(strata) == 1 else None
        instance = instances[index]
        yield Unit(instance["object"], name, stream, instance["group"], stratum, covered, guarantees)


def covered_units(
    record: dict[str, Any], judged_rows: Sequence[dict[str, Any]]
) -> list[tuple[int, int | None, bool]]:
    """(instance, row, covered) of each unit the query's guarantee speaks about: each labelled
    keypoint, or (coverage object) each instance whose keypoints are all labelled (row None)."""
    rows = record["rows"]
    judged = {row["row"]: row["covered"] for row in judged_rows}
    if record["query"]["coverage"] != "object":
        return [(rows[r]["instance"], r, covered) for r, covered in judged.items()]
    units = []
    for index in range(len(record["instances"])):
        members = [r for r, row in enumerate(rows) if row["instance"] == index]
        if members and all(r in judged for r in members):
            units.append((index, None, all(judged[r] for r in members)))
    return units


def group_names(unit: Unit) -> Iterator[tuple[str, str]]:
    """The groups a unit counts in: (level, name)."""
    yield "version", "all"
    yield "object", unit.object
    if unit.keypoint is not None:
        yield "keypoint", f"{unit.object}/{unit.keypoint}"
    if unit.stream:
        yield "stream", unit.stream
    if unit.group:
        yield "group", unit.group
    if unit.stratum is not None:
        yield "stratum", unit.stratum


def _guarantee(guarantee: dict[str, Any]) -> tuple[Any, ...]:
    return (guarantee["n"], guarantee["t"], guarantee["epsilon"], guarantee["delta"])
