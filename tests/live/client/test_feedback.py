"""Feedback end to end through the client, against two replicas sharing PostgreSQL: an
answer retained on one replica (asked with difficulty strata) is labelled through the other, and
both report the same live coverage, per stratum too (the store is the one truth); a second label
is refused."""

from __future__ import annotations

from pathlib import Path

import pytest
from keypoint_client import Conflict, KeypointClient, NotFound, ProblemError

from tests.api.in_process import OnLoopback
from tests.predict_client import instances_of
from tests.samples import Sample, samples_by_image
from tests.service_calls import ADMIN_TOKEN


def test_feedback_and_live_coverage_across_replicas(
    postgres_url: str, tmp_path: Path, samples: list[Sample]
) -> None:
    images = list(samples_by_image(samples).items())[:3]
    with (
        OnLoopback(tmp_path / "a", admin_token=ADMIN_TOKEN, store_url=postgres_url) as a,
        OnLoopback(tmp_path / "b", admin_token=ADMIN_TOKEN, store_url=postgres_url) as b,
        KeypointClient(a.url, token=ADMIN_TOKEN) as on_a,
        KeypointClient(b.url, token=ADMIN_TOKEN) as on_b,
    ):
        labelled = covered = 0
        for path, group in images:
            result = on_a.predict(
                path, instances_of(group), retain=True, stream="cam-1", stratify="difficulty"
            )
            assert result.prediction_id
            assert all(k.guarantee.stratum for i in result.instances for k in i.keypoints)
            labels = [
                {"instance": i, "keypoints": [list(k) for k in s.keypoints]} for i, s in enumerate(group)
            ]
            judged = on_b.send_feedback(result.prediction_id, labels)
            assert judged.calibration_version == result.calibration.version
            labelled, covered = labelled + judged.labelled, covered + judged.covered
        with pytest.raises(Conflict):
            on_a.send_feedback(result.prediction_id, labels)
        with pytest.raises(NotFound):
            on_a.send_feedback("not-a-prediction", labels)
        with pytest.raises(ProblemError) as gone:  # made in 1970: long expired
            on_a.send_feedback("p" + "0" * 32, labels)
        assert gone.value.status == 410
        assert on_a.predict(path, instances_of(group)).prediction_id is None
        live_a, live_b = on_a.live_coverage(), on_b.live_coverage()
        assert live_a == live_b
        pooled = next(g for g in live_a.groups if g.level == "version")
        voted = len(images) - 1  # cam-1's last look is open: it votes once cam-1's next look is labelled
        assert (pooled.labelled, pooled.covered, pooled.looks) == (labelled, covered, voted)
        strata = [g for g in live_a.groups if g.level == "stratum"]
        assert strata and all(g.name.startswith("difficulty bin") for g in strata)
        assert sum(g.labelled for g in strata) == labelled
        stream = next(g for g in live_a.groups if g.level == "stream")
        assert stream.name == "cam-1" and not stream.alarm
        field = on_b.calibrate_from_feedback(stream="cam-1", note="from the robot's labels")
        assert field.version == 2 and not field.activated
        assert field.summary["instances"] == sum(len(group) for _, group in images)
        with pytest.raises(Conflict):
            on_a.calibrate_from_feedback(stream="cam-1")
