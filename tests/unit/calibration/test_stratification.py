"""A version's strata from its ScoreTable: bins per keypoint and group, stored as JSON and read
back equal, per-stratum thresholds equal to calibrating that stratum's scores alone, and rows
matched to their stratum (difficulty within group)."""

from __future__ import annotations

import numpy as np
import pytest

from calibration_store import ObjectScores, ScoreTable
from service.calibration.stratification import (
    DIFFICULTY,
    GROUP,
    StrataSpec,
    VersionStrata,
    answer_rows,
    fit_strata,
    parse_stratify,
    stratified_thresholds,
)
from service.conformal import calibrate, object_scores
from service.conformal.strata import ALL_GROUPS, DifficultySpec
from service.errors import InvalidInput

N, CHANNELS = 400, (3, 5)


@pytest.fixture(scope="module")
def table() -> ScoreTable:
    rng = np.random.default_rng(1)
    gamma = rng.uniform(1, 5, (N, 2))
    p_star = rng.uniform(0.01, 0.2, (N, 2))
    scores = rng.exponential(gamma)  # harder (larger gamma) -> larger scores
    scores[rng.random((N, 2)) < 0.1] = np.nan  # unlabeled keypoints
    groups = tuple(rng.choice(["cam-1", "cam-2", ""], N))
    features = {"gamma": gamma, "peak_probability": p_star, "anisotropy": np.ones((N, 2))}
    block = ObjectScores(
        "mug",
        np.array(CHANNELS),
        tuple(f"r{i}" for i in range(N)),
        {"cov": scores, "var": scores, "peak": scores},
        features=features,
        groups=groups,
    )
    return ScoreTable((block,))


SPEC = StrataSpec(DifficultySpec(("gamma", "peak_probability"), 2, 30), group=True)


def test_strata_round_trip_through_json_and_hold_min_instances(table: ScoreTable) -> None:
    strata = fit_strata(table, SPEC)
    assert strata.groups == ("cam-1", "cam-2")
    assert VersionStrata.from_dict(strata.as_dict()) == strata
    block = table.objects[0]
    labeled = ~np.isnan(block.scores["cov"])
    for j, channel in enumerate(CHANNELS):
        assert sum(strata.bins[channel][ALL_GROUPS].counts) == labeled[:, j].sum()
        assert strata.bins[channel][ALL_GROUPS].n_bins == 4  # 2 x 2 joint bins
        for group in strata.groups:
            bins = strata.bins[channel][group]
            assert sum(bins.counts) == (labeled[:, j] & (np.array(block.groups) == group)).sum()
            assert min(bins.counts) >= 30 and bins.n_bins >= 2


def test_each_stratum_is_calibrated_on_its_own_scores(table: ScoreTable) -> None:
    strata = fit_strata(table, SPEC)
    kinds = frozenset({DIFFICULTY, GROUP})
    thresholds = stratified_thresholds(table, strata, kinds, "cov", "keypoint", 0.1, None)
    block, j = table.objects[0], 1
    rows = (np.array(block.groups) == "cam-2") & ~np.isnan(block.scores["cov"][:, j])
    bins = strata.bins[CHANNELS[j]]["cam-2"]
    assigned = bins.assign({s: block.features[s][rows, j] for s in bins.signals})
    for b, answer in enumerate(thresholds.answers[CHANNELS[j]]["cam-2"]):
        expected = calibrate(block.scores["cov"][rows, j][assigned == b], 0.1)
        assert answer.threshold == expected.threshold and answer.guarantee == expected.guarantee
        assert answer.stratum.group == "cam-2" and answer.stratum.bin == b


def test_rows_get_their_groups_bin_or_a_clear_refusal(table: ScoreTable) -> None:
    strata = fit_strata(table, SPEC)
    kinds = frozenset({DIFFICULTY, GROUP})
    thresholds = stratified_thresholds(table, strata, kinds, "cov", "keypoint", 0.1, None)
    pooled = (np.full(8, 99.0), [calibrate(np.arange(10.0), 0.1).guarantee] * 8)
    features = {"gamma": np.array([1.2, 4.8]), "peak_probability": np.array([0.1, 0.1])}
    channels, instances = np.array([3, 3]), np.array([0, 1])
    answers = answer_rows(
        thresholds, None, pooled, channels, instances, ["cam-1", "cam-1"], features, "refuse"
    )
    low, high = (
        strata.bins[3]["cam-1"].assign({k: v[i : i + 1] for k, v in features.items()})[0] for i in (0, 1)
    )
    assert [s.bin for s in answers.strata] == [low, high] and low < high
    assert answers.values[0] == thresholds.answers[3]["cam-1"][low].threshold
    with pytest.raises(InvalidInput, match=r"instances\[1\]: group 'cam-9' is unknown .*'cam-1', 'cam-2'"):
        answer_rows(thresholds, None, pooled, channels, instances, ["cam-1", "cam-9"], features, "refuse")
    fallback = answer_rows(
        thresholds, None, pooled, channels, instances, ["cam-1", "cam-9"], features, "pooled"
    )
    assert fallback.strata[1].kinds == "pooled" and fallback.values[1] == 99.0
    with pytest.raises(InvalidInput, match="no scores for keypoint channel 7"):  # an object the version lacks
        answer_rows(thresholds, None, pooled, np.array([7]), np.array([0]), ["cam-1"], features, "refuse")


def test_stratify_values_and_impossible_specs_are_refused(table: ScoreTable) -> None:
    assert (
        parse_stratify("difficulty group") == parse_stratify(["group", "difficulty"]) == {DIFFICULTY, GROUP}
    )
    assert parse_stratify("none") == frozenset()
    with pytest.raises(InvalidInput, match="stratify 'both'"):
        parse_stratify("both")
    block = table.objects[0]
    bare = ScoreTable((ObjectScores("mug", block.keypoint_ids, block.instance_refs, block.scores),))
    with pytest.raises(InvalidInput, match="group labels"):
        fit_strata(bare, StrataSpec(group=True))
    with pytest.raises(InvalidInput, match="heatmap features"):
        fit_strata(bare, StrataSpec(DifficultySpec()))


def test_object_scope_calibrates_each_group_on_its_fully_labeled_instances(table: ScoreTable) -> None:
    strata = fit_strata(table, SPEC)
    thresholds = stratified_thresholds(table, strata, frozenset({GROUP}), "cov", "object", 0.2, None)
    block = table.objects[0]
    rows = np.array(block.groups) == "cam-1"
    expected = calibrate(object_scores(block.scores["cov"][rows]), 0.2)
    for channel in CHANNELS:
        (answer,) = thresholds.answers[channel]["cam-1"]
        assert answer.threshold == expected.threshold and answer.guarantee == expected.guarantee
        assert answer.stratum.kinds == "group" and answer.stratum.group == "cam-1"
