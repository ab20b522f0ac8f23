"""The manifest is a contract: what would be served wrongly or silently ignored is refused.

Every refusal is a ``ManifestError`` whose lines read ``<file>: <field path>: <problem>``.
Cases edit a copy of the bundled manifest (parsed JSON), so each shows one rule on a
manifest that is otherwise the real one.
"""

from __future__ import annotations

import copy
import json
from collections.abc import Callable
from pathlib import Path

import pytest

from service.detector.manifest import (
    MANIFEST_FILENAME,
    Manifest,
    ManifestError,
    load_manifest,
    validate_manifest,
)
from service.infra.settings import DEFAULT_MODEL_DIR

SOURCE = "model/manifest.json"


@pytest.fixture(scope="module")
def bundled() -> dict:
    return json.loads((DEFAULT_MODEL_DIR / MANIFEST_FILENAME).read_text(encoding="utf-8"))


def refusal(document: dict, edit: Callable[[dict], object]) -> ManifestError:
    document = copy.deepcopy(document)
    edit(document)
    with pytest.raises(ManifestError) as raised:
        validate_manifest(document, SOURCE)
    return raised.value


def edited(document: dict, edit: Callable[[dict], object]) -> Manifest:
    document = copy.deepcopy(document)
    edit(document)
    return validate_manifest(document, SOURCE)


def only_line(error: ManifestError) -> str:
    lines = str(error).splitlines()
    assert len(lines) == 1, lines
    return lines[0]


def test_the_bundled_manifest_passes_and_round_trips(bundled: dict) -> None:
    manifest = load_manifest(DEFAULT_MODEL_DIR)
    assert manifest.num_keypoints == len(bundled["keypoints"])
    assert validate_manifest(manifest.model_dump(mode="json"), SOURCE) == manifest


def test_duplicate_keypoint_names_are_refused_naming_both_entries(bundled: dict) -> None:
    error = refusal(bundled, lambda m: m["keypoints"][3].update(name="duck_kp0"))
    assert only_line(error).startswith(
        f"{SOURCE}: keypoints[3].name: 'duck_kp0' is also the name of keypoints[0]"
    )
    assert "channels 0 and 3" in str(error) and "unique" in str(error)
    assert error.problems == [("keypoints[3].name", error.problems[0][1])]


def test_names_must_be_unique_across_objects(bundled: dict) -> None:
    """Calibration reports map keypoint names to values: a mug keypoint may not reuse a duck's name."""
    error = refusal(bundled, lambda m: m["keypoints"][9].update(name="duck_kp2"))
    assert only_line(error).startswith(
        f"{SOURCE}: keypoints[9].name: 'duck_kp2' is also the name of keypoints[2]"
    )


def test_duplicate_and_out_of_range_indices_name_the_entry(bundled: dict) -> None:
    error = refusal(bundled, lambda m: m["keypoints"][5].update(index=4))
    assert only_line(error).startswith(f"{SOURCE}: keypoints[5].index: 4 is also keypoints[4].index")
    error = refusal(bundled, lambda m: m["keypoints"][5].update(index=48))
    assert only_line(error).startswith(f"{SOURCE}: keypoints[5].index: is 48") and "0..47" in str(error)


def test_top_k_must_fit_the_heatmap(bundled: dict) -> None:
    pixels = bundled["output"]["height"] * bundled["output"]["width"]
    error = refusal(bundled, lambda m: m["heatmap"].update(top_k=pixels + 1))
    assert only_line(error) == (
        f"{SOURCE}: heatmap.top_k: is {pixels + 1} but a 64x64 heatmap (output.height x output.width) "
        f"has {pixels} pixels; use 1..{pixels}"
    )
    assert edited(bundled, lambda m: m["heatmap"].update(top_k=pixels)).heatmap.top_k == pixels
    assert only_line(refusal(bundled, lambda m: m["heatmap"].update(top_k=0))).startswith(
        f"{SOURCE}: heatmap.top_k: "
    )


def test_an_omitted_top_k_is_the_default_capped_at_the_heatmap_size(bundled: dict) -> None:
    def small_heatmap(m: dict) -> None:
        m["output"].update(height=8, width=6)
        m["heatmap"].pop("top_k")

    assert edited(bundled, small_heatmap).heatmap.top_k == 48
    assert edited(bundled, lambda m: m["heatmap"].pop("top_k")).heatmap.top_k == 100
    error = refusal(bundled, lambda m: (small_heatmap(m), m["heatmap"].update(top_k=49)))
    assert only_line(error).startswith(f"{SOURCE}: heatmap.top_k: is 49 but a 8x6 heatmap")


@pytest.mark.parametrize("mode", ["anchor", "relu"])
def test_a_temperature_needs_softmax(bundled: dict, mode: str) -> None:
    error = refusal(bundled, lambda m: m["heatmap"].update(normalization=mode, temperature=0.5))
    assert only_line(error) == (
        f"{SOURCE}: heatmap.temperature: is 0.5 but normalization {mode!r} does not use a temperature "
        "(only softmax does); remove it or set heatmap.normalization to softmax"
    )
    softmax = edited(bundled, lambda m: m["heatmap"].update(normalization="softmax", temperature=0.5))
    assert softmax.heatmap.temperature == 0.5


def test_every_problem_gets_its_own_line(bundled: dict) -> None:
    def two_problems(m: dict) -> None:
        m["keypoints"][3]["name"] = "duck_kp0"
        m["heatmap"]["temperature"] = 2.0

    error = refusal(bundled, two_problems)
    assert sorted(field for field, _ in error.problems) == ["heatmap.temperature", "keypoints[3].name"]
    assert [line.split(": ")[:2] for line in str(error).splitlines()] == [
        [SOURCE, field] for field, _ in error.problems
    ]


def test_objects_must_agree_with_the_keypoints(bundled: dict) -> None:
    cases: list[tuple[Callable[[dict], object], str]] = [
        (
            lambda m: m["keypoints"][3].update(object="duk"),
            "keypoints[3].object: 'duk' (of keypoint 'duck_kp3')",
        ),
        (lambda m: m["objects"][1].update(name="duck"), "objects[1].name: 'duck' is also objects[0].name"),
        (
            lambda m: m["objects"][0]["keypoints"].__setitem__(7, 8),
            "objects[0].keypoints[7]: keypoint 8 ('mug_kp0')",
        ),
        (lambda m: m["objects"][0]["keypoints"].__setitem__(7, -1), "objects[0].keypoints[7]: "),
    ]
    for edit, start in cases:
        assert str(refusal(bundled, edit)).startswith(f"{SOURCE}: {start}")

    def listed_twice(m: dict) -> None:
        m["objects"][0]["keypoints"][7] = 6
        m["objects"][0].pop("keypoints_3d")

    lines = str(refusal(bundled, listed_twice)).splitlines()
    assert lines == [f"{SOURCE}: objects[0].keypoints[7]: channel 6 is already keypoints[6]"]


def test_channel_statistics_must_match_the_colour(bundled: dict) -> None:
    error = refusal(bundled, lambda m: m["input"].update(color="GRAY"))
    assert [field for field, _ in error.problems] == ["input.mean", "input.std"]
    assert "color GRAY has 1 channel(s)" in str(error)


def test_unknown_fields_and_bad_json_are_located(bundled: dict, tmp_path: Path) -> None:
    error = refusal(bundled, lambda m: m["heatmap"].update(temprature=0.5))
    assert only_line(error).startswith(f"{SOURCE}: heatmap.temprature: is not a manifest field")
    (tmp_path / MANIFEST_FILENAME).write_text('{"name": "m",\n  "input": }', encoding="utf-8")
    with pytest.raises(ManifestError) as raised:
        load_manifest(tmp_path)
    assert only_line(raised.value).startswith(
        f"{tmp_path / MANIFEST_FILENAME}: line 2 column 12: not valid JSON"
    )


def test_non_finite_numbers_are_refused(bundled: dict, tmp_path: Path) -> None:
    """Python's json reads NaN and Infinity; an infinite temperature would fail every predict instead."""
    manifest = copy.deepcopy(bundled)
    manifest["heatmap"].update(normalization="softmax", temperature=float("inf"))
    manifest["input"]["mean"][1] = float("nan")
    (tmp_path / MANIFEST_FILENAME).write_text(json.dumps(manifest), encoding="utf-8")
    with pytest.raises(ManifestError) as raised:
        load_manifest(tmp_path)
    assert [field for field, _ in raised.value.problems] == ["input.mean[1]", "heatmap.temperature"]
    assert "Infinity" in (tmp_path / MANIFEST_FILENAME).read_text() and "finite" in str(raised.value)
