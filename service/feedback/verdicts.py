"""The verdicts of a label: what live coverage counts of a labelled prediction, judged once when the
label is stored (about 2 KB beside an 11 KB record; docs/feedback.md). The tally (covered units per
group, the look) varies between labels; the shape (version, guarantee, query, groups, each unit's
floor as its guarantees (n, t, epsilon, delta)) is one JSON text a stream's frames share.
"""

from __future__ import annotations

import json
from collections.abc import Iterator, Sequence
from operator import itemgetter
from typing import Any

from calibration_store import LabelVerdicts, RetainedPrediction

#: a row's guarantee as the shape keeps it
_GUARANTEE = itemgetter("n", "t", "epsilon", "delta")


def verdicts(prediction: RetainedPrediction, keypoint_names: list[str]) -> LabelVerdicts:
    """The shape (JSON text) and tally (``look``, ``covered`` per group) of a labelled prediction."""
    record = prediction.record
    query = record["query"]
    floors: dict[tuple, int] = {}
    groups: dict[tuple[str, str], tuple[list[int], list[list[int]]]] = {}
    judged = (prediction.labels or {}).get("rows", [])
    for guarantees, unit_covered, names in _units(record, judged, keypoint_names, prediction.stream):
        floor = floors.setdefault(guarantees, len(floors))
        for name in names:
            covered, runs = groups.setdefault(name, ([0], []))
            covered[0] += unit_covered
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
    # rows kept before looks: one look each
    tally = {"look": record.get("look", prediction.id), "covered": [c[0] for c, _ in groups.values()]}
    return LabelVerdicts(json.dumps(shape, separators=(",", ":")), tally)


def _units(
    record: dict[str, Any], judged_rows: Sequence[dict[str, Any]], keypoint_names: list[str], stream: str
) -> Iterator[tuple[tuple[tuple[Any, ...], ...], bool, list[tuple[str, str]]]]:
    """Per judged unit: the guarantees of its rows, whether it is covered, its groups."""
    rows, instances = record["rows"], record["instances"]
    for index, row, covered in covered_units(record, judged_rows):
        members = [r for r, kept in enumerate(rows) if kept["instance"] == index] if row is None else [row]
        guarantees = tuple(dict.fromkeys(_GUARANTEE(rows[r]["guarantee"]) for r in members))
        instance = instances[index]
        groups = [("version", "all"), ("object", instance["object"])]
        if row is not None:
            groups.append(("keypoint", f"{instance['object']}/{keypoint_names[rows[row]['channel']]}"))
        if stream:
            groups.append(("stream", stream))
        if instance["group"]:
            groups.append(("group", instance["group"]))
        strata = {rows[r].get("stratum") for r in members}  # one per instance with coverage object
        if len(strata) == 1 and (stratum := strata.pop()) is not None:  # the Mondrian stratum that served it
            groups.append(("stratum", stratum))
        yield guarantees, covered, groups


def covered_units(
    record: dict[str, Any], judged_rows: Sequence[dict[str, Any]]
) -> list[tuple[int, int | None, bool]]:
    """(instance, row, covered) per labelled keypoint, or complete instance (coverage object)."""
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
