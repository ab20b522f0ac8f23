"""Feedback on served predictions in process (the ASGI app, the real model, SQLite): a retained answer
carries a prediction_id, its true points are judged against the sets served and stored once, with
every refusal a clear 4xx, the feedback token's own scope, and the audit trail."""

from __future__ import annotations

import sqlite3
import time
from collections.abc import Iterator
from dataclasses import asdict
from datetime import UTC, datetime, timedelta
from pathlib import Path

import pytest

from calibration_store import NewAuditEntry, sqlite_path
from service.api.predict.predict_schemas import PredictResponse
from service.feedback.confidence_sequence import promised_floor
from service.feedback.live_coverage import LiveCoverageReader
from service.feedback.retention import new_prediction_id
from tests.api.in_process import InProcess
from tests.predict_client import contains, instances_of, predict_json, predict_ok
from tests.samples import Sample, samples_by_image
from tests.service_calls import ADMIN_TOKEN, assert_problem

FEEDBACK_TOKEN = "robot-feedback-token-0001"


@pytest.fixture(scope="module")
def api(tmp_path_factory: pytest.TempPathFactory) -> Iterator[InProcess]:
    folder = tmp_path_factory.mktemp("feedback")
    tokens = folder / "tokens"
    tokens.write_text(f"alice:{ADMIN_TOKEN}-alice\nfeedback robot-1:{FEEDBACK_TOKEN}\n")
    with InProcess(folder / "data", admin_token=ADMIN_TOKEN, admin_tokens_file=str(tokens)) as service:
        yield service


def sender(token: str = FEEDBACK_TOKEN) -> dict[str, str]:
    return {"Authorization": f"Bearer {token}"}


def labels_of(group: list[Sample]) -> dict:
    return {"instances": [{"instance": i, "keypoints": s.keypoints} for i, s in enumerate(group)]}


def first_image(samples: list[Sample]) -> tuple[bytes, list[Sample]]:
    path, group = next(iter(samples_by_image(samples).items()))
    return Path(path).read_bytes(), group


def retained(api: InProcess, image: bytes, group: list[Sample], **options) -> dict:
    return predict_ok(api.client, image, {"instances": instances_of(group), "retain": True, **options})


def test_an_answer_not_retained_has_no_prediction_id(api: InProcess, samples: list[Sample]) -> None:
    image, group = first_image(samples)
    answer = predict_ok(api.client, image, {"instances": instances_of(group)})
    assert "prediction_id" not in answer


def test_a_retained_answer_is_the_documented_body_with_its_id(api: InProcess, samples: list[Sample]) -> None:
    image, group = first_image(samples)
    for options in ({"retain": True}, {"adaptive": True, "stream": "cam-doc"}):
        response = predict_json(api.client, image, {"instances": instances_of(group), **options})
        assert response.status_code == 200, response.text
        body = PredictResponse.model_validate_json(response.content)
        assert body.prediction_id and body.model_dump_json().encode() == response.content
        assert (body.adaptive is not None) == ("adaptive" in options)


def test_feedback_is_judged_against_the_sets_served_and_stored_once(
    api: InProcess, samples: list[Sample]
) -> None:
    image, group = first_image(samples)
    answer = retained(api, image, group, stream="cam-1")
    prediction_id = answer["prediction_id"]
    response = api.client.post(f"/v1/feedback/{prediction_id}", json=labels_of(group), headers=sender())
    assert response.status_code == 200, response.text
    judged = response.json()
    served = [kp for instance in answer["instances"] for kp in instance["keypoints"]]
    truths = [(x, y, v) for s in group for x, y, v in s.keypoints]
    expected = [contains(kp["set"], (x, y)) for kp, (x, y, v) in zip(served, truths, strict=True) if v]
    assert [k["covered"] for k in judged["keypoints"]] == expected
    assert judged["labelled"] == len(expected) and judged["covered"] == sum(expected)
    assert set(judged["keypoints"][0]["scores"]) == {"peak", "var", "cov"}
    again = api.client.post(f"/v1/feedback/{prediction_id}", json=labels_of(group), headers=sender())
    assert_problem(again, 409, "already")
    log = api.client.get("/v1/admin/audit", headers=api.admin).json()
    entries = [e for e in log["entries"] if e["action"] == "feedback"]
    assert entries[0]["who"] == "robot-1" and entries[0]["outcome"] == "refused"
    assert entries[1]["outcome"] == "labelled" and entries[1]["details"]["prediction_id"] == prediction_id


def test_some_keypoints_of_some_instances(api: InProcess, samples: list[Sample]) -> None:
    image, group = first_image(samples)
    answer = retained(api, image, group)
    prediction_id = answer["prediction_id"]
    last = len(group) - 1
    labelled = [j for j, (_, _, v) in enumerate(group[last].keypoints) if v][:2]
    keypoints = [(x, y, v if j in labelled else 0) for j, (x, y, v) in enumerate(group[last].keypoints)]
    body = {"instances": [{"instance": last, "keypoints": keypoints}]}
    response = api.client.post(f"/v1/feedback/{prediction_id}", json=body, headers=sender())
    assert response.status_code == 200, response.text
    judged = response.json()["keypoints"]
    served = answer["instances"][last]["keypoints"]
    assert [(k["instance"], k["index"]) for k in judged] == [(last, served[j]["index"]) for j in labelled]
    assert len(judged) == 2


def test_unknown_and_expired_ids(api: InProcess) -> None:
    unknown = new_prediction_id(datetime.now(UTC))
    assert_problem(api.client.post(f"/v1/feedback/{unknown}", json={"instances": []}, headers=sender()), 422)
    body = {"instances": [{"instance": 0, "keypoints": [[1, 1, 2]]}]}
    assert_problem(api.client.post(f"/v1/feedback/{unknown}", json=body, headers=sender()), 404, "retain")
    assert_problem(api.client.post("/v1/feedback/not-an-id", json=body, headers=sender()), 404)
    beyond_clocks = "p" + "f" * 32  # a well-formed id from a time no clock reaches
    assert_problem(api.client.post(f"/v1/feedback/{beyond_clocks}", json=body, headers=sender()), 404)
    old = new_prediction_id(datetime.now(UTC) - timedelta(days=8))
    assert_problem(api.client.post(f"/v1/feedback/{old}", json=body, headers=sender()), 410, "no longer kept")


def test_malformed_labels_are_422_naming_each_problem(api: InProcess, samples: list[Sample]) -> None:
    image, group = first_image(samples)
    prediction_id = retained(api, image, group)["prediction_id"]
    k = len(group[0].keypoints)
    cases = {
        "is not an instance": [{"instance": len(group), "keypoints": group[0].keypoints}],
        "entries but object": [{"instance": 0, "keypoints": group[0].keypoints[:-1]}],
        "visibility 3": [{"instance": 0, "keypoints": [(1.0, 1.0, 3)] * k}],
        "outside the": [{"instance": 0, "keypoints": [(-5.0, 1.0, 2)] * k}],
        "no keypoint is labelled": [{"instance": 0, "keypoints": [(0.0, 0.0, 0)] * k}],
        "labelled twice": [{"instance": 0, "keypoints": group[0].keypoints}] * 2,
        "not COCO's flat list": [{"instance": 0, "keypoints": [v for p in group[0].keypoints for v in p]}],
    }
    for fragment, instances in cases.items():
        response = api.client.post(
            f"/v1/feedback/{prediction_id}", json={"instances": instances}, headers=sender()
        )
        assert assert_problem(response, 422, fragment)["title"] == "Invalid input"
    assert_problem(
        api.client.post(f"/v1/feedback/{prediction_id}", json={"instances": [], "x": 1}, headers=sender()),
        422,
    )
    # nothing was stored by the refusals: the labels are still taken once
    response = api.client.post(f"/v1/feedback/{prediction_id}", json=labels_of(group), headers=sender())
    assert response.status_code == 200, response.text


def test_who_may_send_feedback(api: InProcess, samples: list[Sample]) -> None:
    image, group = first_image(samples)
    prediction_id = retained(api, image, group)["prediction_id"]
    url = f"/v1/feedback/{prediction_id}"
    assert_problem(api.client.post(url, json=labels_of(group)), 401)
    assert_problem(
        api.client.post(url, json=labels_of(group), headers=sender("wrong-token-wrong-token")), 401
    )
    # the feedback token is no admin token
    assert_problem(api.client.get("/v1/admin/audit", headers=sender()), 401)
    assert api.client.post(url, json=labels_of(group), headers=api.admin).status_code == 200


def test_feedback_is_off_without_tokens(tmp_path: Path, samples: list[Sample]) -> None:
    with InProcess(tmp_path / "data", feedback_retain_share=1.0) as service:
        image, group = first_image(samples)
        answer = predict_ok(service.client, image, {"instances": instances_of(group)})
        assert answer["prediction_id"]  # sampled: every answer retained at share 1
        response = service.client.post(f"/v1/feedback/{answer['prediction_id']}", json=labels_of(group))
        assert_problem(response, 403, "feedback name:token")


def test_the_oldest_go_first_beyond_the_size_bound(tmp_path: Path, samples: list[Sample]) -> None:
    with InProcess(tmp_path / "data", admin_token=ADMIN_TOKEN, feedback_max_retained=2) as service:
        image, group = first_image(samples)
        ids = [retained(service, image, group)["prediction_id"] for _ in range(3)]
        first = service.client.post(f"/v1/feedback/{ids[0]}", json=labels_of(group), headers=service.admin)
        assert_problem(first, 410, "CKS_FEEDBACK_MAX_RETAINED")
        last = service.client.post(f"/v1/feedback/{ids[2]}", json=labels_of(group), headers=service.admin)
        assert last.status_code == 200, last.text


def test_a_png_answer_is_not_retained(api: InProcess, samples: list[Sample]) -> None:
    image, group = first_image(samples)
    response = predict_json(
        api.client, image, {"instances": instances_of(group), "retain": True}, path="/v1/predict/png"
    )
    assert response.status_code == 200 and response.headers["content-type"] == "image/png"


def send_all(service: InProcess, samples: list[Sample], shift: float, stream: str, **options) -> list[dict]:
    """Every sample image predicted (retained) and labelled, the labels moved ``shift`` pixels (right,
    or left near the right edge); the answers."""
    answers = []
    for path, group in samples_by_image(samples).items():
        answer = retained(service, Path(path).read_bytes(), group, stream=stream, **options)
        answers.append(answer)
        moved = [
            {
                "instance": i,
                "keypoints": [
                    (x + shift if x + shift <= s.width else x - shift, y, v) for x, y, v in s.keypoints
                ],
            }
            for i, s in enumerate(group)
        ]
        response = service.client.post(
            f"/v1/feedback/{answer['prediction_id']}", json={"instances": moved}, headers=service.admin
        )
        assert response.status_code == 200, response.text
    return answers


def test_live_coverage_holds_on_true_labels_and_alarms_on_labels_the_sets_miss(
    tmp_path: Path, samples: list[Sample]
) -> None:
    with InProcess(tmp_path / "data", admin_token=ADMIN_TOKEN, feedback_alarm_level=0.05) as service:
        send_all(service, samples, 0.0, "cam-true")
        live = service.client.get("/v1/admin/coverage/live", headers=service.admin)
        assert live.status_code == 200, live.text
        report = live.json()
        assert report["alarm_level"] == 0.05 and not report["alarm"]
        pooled = next(g for g in report["groups"] if g["level"] == "version")
        labelled = sum(v > 0 for s in samples for _, _, v in s.keypoints)
        looks = len(samples_by_image(samples)) - 1  # the stream's last look votes once the next one comes
        assert pooled["labelled"] == labelled and pooled["looks"] == looks
        assert pooled["lower"] <= pooled["covered"] / pooled["labelled"] <= pooled["upper"]
        assert {g["level"] for g in report["groups"]} == {"version", "object", "keypoint", "stream"}
        send_all(service, samples, 60.0, "cam-moved")  # labels of another scene: the sets miss them
        report = service.client.get("/v1/admin/coverage/live", headers=service.admin).json()
        moved = next(g for g in report["groups"] if g["level"] == "stream" and g["name"] == "cam-moved")
        assert moved["covered"] == 0 and moved["alarm"] and moved["upper"] < moved["floor"]
        true = next(g for g in report["groups"] if g["level"] == "stream" and g["name"] == "cam-true")
        assert not true["alarm"]
        metrics = service.client.get("/metrics").text
        assert (
            'cks_feedback_coverage_alarm{coverage="keypoint",epsilon="0.1",level="stream",name="cam-moved"'
            in metrics
        )
        assert_problem(service.client.get("/v1/admin/coverage/live"), 401)


def test_adaptive_sets_follow_the_streams_feedback_and_survive_a_restart(
    tmp_path: Path, samples: list[Sample]
) -> None:
    image, group = first_image(samples)
    options = {"instances": instances_of(group), "stream": "cam-9", "adaptive": True, "epsilon": 0.1}
    gamma = 0.01
    with InProcess(tmp_path / "data", {"ACI_GAMMA": gamma}, admin_token=ADMIN_TOKEN) as service:
        for refused, problem in (({"stream": None}, "needs stream"), ({"delta": 0.1}, "no delta")):
            response = predict_json(service.client, image, {**options, **refused})
            assert_problem(response, 422, problem)
        first = predict_ok(service.client, image, options)
        assert first["adaptive"] == {
            "guarantee": "adaptive",
            "epsilon": 0.1,
            "alpha": 0.1,
            "served_epsilon": 0.1,
            "gamma": gamma,
            "steps": 0,
            "miscoverage": None,
            "label_lag": 0,
            "long_run_bound": None,
        }
        plain = predict_ok(service.client, image, {"instances": instances_of(group)})
        assert first["instances"] == plain["instances"]  # alpha_1 = epsilon: the calibration's sets
        moved = [
            {"instance": i, "keypoints": [(5.0, 5.0, v) for _, _, v in s.keypoints]}
            for i, s in enumerate(group)
        ]
        url = f"/v1/feedback/{first['prediction_id']}"
        judged = service.client.post(url, json={"instances": moved}, headers=service.admin).json()
        misses = judged["labelled"] - judged["covered"]
    with InProcess(tmp_path / "data", {"ACI_GAMMA": gamma}, admin_token=ADMIN_TOKEN) as service:
        second = predict_ok(service.client, image, options)["adaptive"]
        assert second["steps"] == judged["labelled"] and misses > 0
        assert second["alpha"] == pytest.approx(0.1 + gamma * (0.1 * judged["labelled"] - misses))
        assert second["served_epsilon"] < 0.1  # missed labels: larger sets
        # the answer's labels were learned one after the other, all served at one level: lags 0..T-1
        assert second["label_lag"] == judged["labelled"] - 1
        bound = (0.9 + gamma * judged["labelled"]) / (gamma * judged["labelled"])
        assert second["long_run_bound"] == pytest.approx(bound)
        live = service.client.get("/v1/admin/coverage/live", headers=service.admin).json()
        adaptive = [g for g in live["groups"] if g["guarantee"] == "adaptive"]
        assert adaptive and not any(g["alarm"] for g in adaptive)


def test_live_coverage_counts_each_stratum_against_its_own_promise(
    tmp_path: Path, samples: list[Sample]
) -> None:
    level = 0.05
    with InProcess(tmp_path / "data", admin_token=ADMIN_TOKEN, feedback_alarm_level=level) as service:
        answers = send_all(service, samples, 0.0, "cam-true", stratify="difficulty")
        labelled_by_bin: dict[str, int] = {}
        floors: dict[str, list[float]] = {}
        for answer, group in zip(answers, samples_by_image(samples).values(), strict=True):
            for instance, sample in zip(answer["instances"], group, strict=True):
                for keypoint, (_, _, v) in zip(instance["keypoints"], sample.keypoints, strict=True):
                    guarantee = keypoint["guarantee"]
                    name = f"difficulty bin {guarantee['stratum']['bin']}"
                    labelled_by_bin[name] = labelled_by_bin.get(name, 0) + (v > 0)
                    if v > 0:
                        floor = promised_floor(guarantee["n"], guarantee["t"], 0.1, None, level / 2)
                        floors.setdefault(name, []).append(floor)
        report = service.client.get("/v1/admin/coverage/live", headers=service.admin).json()
        strata = {g["name"]: g for g in report["groups"] if g["level"] == "stratum"}
        assert len(strata) > 1 and {n: g["labelled"] for n, g in strata.items()} == {
            name: count for name, count in labelled_by_bin.items() if count
        }
        for name, stratum in strata.items():  # each against its own threshold's Beta band
            assert stratum["floor"] == pytest.approx(min(floors[name]))
            assert not stratum["alarm"] and stratum["lower"] <= stratum["look_mean"] <= stratum["upper"]
        # no group is stratified here: every row falls back to the pooled threshold, and is counted so
        send_all(service, samples, 60.0, "cam-moved", stratify="group", group_fallback="pooled")
        report = service.client.get("/v1/admin/coverage/live", headers=service.admin).json()
        after = {g["name"]: g for g in report["groups"] if g["level"] == "stratum"}
        assert {name: after[name] for name in strata} == strata
        pooled = after["pooled"]
        assert pooled["covered"] == 0 and pooled["alarm"] and pooled["upper"] < pooled["floor"]
        assert pooled["labelled"] == sum(labelled_by_bin.values())
        metrics = service.client.get("/metrics").text
        assert 'level="stratum",name="difficulty bin 0"' in metrics


def test_live_coverage_folds_each_label_once_as_it_arrives(tmp_path: Path, samples: list[Sample]) -> None:
    level = 0.05
    with InProcess(tmp_path / "data", admin_token=ADMIN_TOKEN, feedback_alarm_level=level) as service:
        state = service.app.state.service
        live = "/v1/admin/coverage/live"
        first = send_all(service, samples, 0.0, "cam-a")
        service.client.get(live, headers=service.admin)  # read: these labels are folded
        send_all(service, samples, 60.0, "cam-b")
        report = service.client.get(live, headers=service.admin).json()
        names = [k.name for k in state.detector.manifest.keypoints]
        fresh = LiveCoverageReader(state.store, state.detector.model_hash, names, 10**6, level).report()
        assert report["groups"] == [asdict(g) for g in fresh]  # read in two goes, or all at once: the same

        image, group = first_image(samples)
        late = retained(service, image, group, stream="cam-late")  # its label commits late, stamped early
        state.retention.flush()
        labels = state.store.retained_prediction(first[0]["prediction_id"]).labels
        stamped = datetime.now(UTC) - timedelta(seconds=30)  # within live_coverage.SETTLE of the newest
        entry = NewAuditEntry(state.detector.model_hash, "late", "feedback", "labelled", version=1)
        state.store.label_prediction(late["prediction_id"], labels, "late", stamped, entry)
        report = service.client.get(live, headers=service.admin).json()
        streams = {g["name"]: g for g in report["groups"] if g["level"] == "stream"}
        assert streams["cam-late"]["labelled"] == len(labels["rows"])
        assert streams["cam-late"]["looks"] == 0  # its one look is open: no later look of cam-late
        assert service.client.get(live, headers=service.admin).json() == report  # nothing counted twice


def test_stored_verdicts_count_as_the_records_judged_on_read(tmp_path: Path, samples: list[Sample]) -> None:
    """A label's verdicts are stored with it; rows labelled before that (schema 9) are judged from
    their records on read: the same labels give the same votes, looks, alarms and figures."""
    level = 0.05
    with InProcess(tmp_path / "data", admin_token=ADMIN_TOKEN, feedback_alarm_level=level) as service:
        state = service.app.state.service
        send_all(service, samples, 0.0, "cam-true", stratify="difficulty")
        send_all(service, samples, 0.0, "cam-objects", coverage="object", delta=0.1)
        send_all(service, samples, 60.0, "cam-moved", stratify="group", group_fallback="pooled")
        send_all(service, samples, 60.0, "cam-adaptive", adaptive=True)
        send_all(service, samples, 2.0, None, epsilon=0.2)  # no stream: one look per answer
        names = [k.name for k in state.detector.manifest.keypoints]
        model_hash = state.detector.model_hash

        def fresh() -> list:
            return LiveCoverageReader(state.store, model_hash, names, 10**6, level).report()

        ids = [i for i, _ in state.store.labelled_since(model_hash, None)]
        assert len(state.store.label_verdicts(ids)) == len(ids)
        stored = fresh()
        with sqlite3.connect(sqlite_path(state.settings.storage.resolved_url)) as connection:
            connection.execute("DELETE FROM calib_verdicts")  # as if labelled before verdicts were stored
        assert state.store.label_verdicts(ids) == {}
        judged = fresh()
    assert judged == stored
    assert {g.level for g in stored} == {"version", "object", "keypoint", "stream", "stratum"}
    assert {g.guarantee for g in stored} == {"exchangeable", "adaptive"}
    assert {g.coverage for g in stored} == {"keypoint", "object"}
    assert any(g.alarm for g in stored) and not all(g.alarm for g in stored)


def test_a_metrics_scrape_never_waits_for_live_coverage(tmp_path: Path, samples: list[Sample]) -> None:
    with InProcess(tmp_path / "data", admin_token=ADMIN_TOKEN) as service:
        send_all(service, samples, 0.0, "cam-a")
        gauge = 'cks_feedback_coverage_looks{coverage="keypoint",epsilon="0.1",level="stream",name="cam-a"'
        # the first scrape of a process: nothing counted yet, so nothing to say, and it does not wait
        assert gauge not in service.client.get("/metrics").text
        deadline = time.monotonic() + 30
        while gauge not in (text := service.client.get("/metrics").text) and time.monotonic() < deadline:
            time.sleep(0.05)  # the count the scrape started, in the background
        looks = len(samples_by_image(samples)) - 1  # voted: all but the stream's last, still open
        assert f'{gauge},nonconformity="cov",version="1"}} {float(looks)}' in text


def test_adaptive_sets_count_the_lag_of_labels_that_arrive_after_later_answers_labels(
    tmp_path: Path, samples: list[Sample]
) -> None:
    """A label learned after the labels of answers served later has their updates as its lag
    (the long-run bound's L), not only the lag within its own answer."""
    image, group = first_image(samples)
    options = {"instances": instances_of(group), "stream": "cam-7", "adaptive": True, "epsilon": 0.1}
    labels = {
        "instances": [{"instance": i, "keypoints": s.keypoints} for i, s in enumerate(group)],
    }
    with InProcess(tmp_path / "data", {"ACI_GAMMA": 0.01}, admin_token=ADMIN_TOKEN) as service:
        early, late = (predict_ok(service.client, image, options) for _ in range(2))
        counts = []
        for answer in (late, early):  # the early answer's labels come last
            url = f"/v1/feedback/{answer['prediction_id']}"
            counts.append(service.client.post(url, json=labels, headers=service.admin).json()["labelled"])
        after = predict_ok(service.client, image, options)["adaptive"]
    assert after["steps"] == sum(counts)
    assert after["label_lag"] == sum(counts) - 1  # the early answer's last label: every update before it
