"""The predict response written from plain data (predict_presenter.predict_json) is exactly what
the response models write: every field, in order, left out where the schema leaves it out.

In process, on the real model and the bundled calibration in a real SQLite store; every kind
of set (ball, ellipse, unbounded), statistics, Mondrian strata and pose blocks.
"""

from __future__ import annotations

import json
from collections.abc import Iterator
from pathlib import Path

import pytest

from service.api.predict.predict_input import predict_query
from service.api.predict.predict_presenter import predict_body, predict_json, predict_response
from service.api.predict.predict_schemas import PredictParameters, PredictResponse
from service.infra.settings import Settings
from service.serving.container import ServiceState, build_state


@pytest.fixture(scope="module")
def state(model_path: Path, tmp_path_factory: pytest.TempPathFactory) -> Iterator[ServiceState]:
    settings = Settings(model_dir=model_path, data_dir=tmp_path_factory.mktemp("presenter"))
    state = build_state(settings)
    yield state
    state.close()


@pytest.fixture(scope="module")
def scene(samples_dir: Path, coco: dict) -> tuple[bytes, list[dict], list[str]]:
    """The sample image with the most objects: its bytes, annotations and object names."""
    categories = {c["id"]: c["name"] for c in coco["categories"]}
    by_image: dict[int, list[dict]] = {}
    for annotation in coco["annotations"]:
        by_image.setdefault(annotation["image_id"], []).append(annotation)
    image_id = max(by_image, key=lambda i: len(by_image[i]))
    image = next(i for i in coco["images"] if i["id"] == image_id)
    annotations = by_image[image_id]
    names = [categories[a["category_id"]] for a in annotations]
    return (samples_dir / image["file_name"]).read_bytes(), annotations, names


OPTIONS = [
    {},
    {"include_statistics": True},
    {"nonconformity": "var", "include_statistics": True},
    {"nonconformity": "peak", "coverage": "object", "delta": 0.1},
    {"epsilon": 0.001},  # too few scores: unbounded sets
    {"stratify": "difficulty", "group_fallback": "pooled", "epsilon": 0.2},
    {"stratify": "group", "group_fallback": "pooled"},
    {"coverage": "object", "epsilon": 0.3, "pose": "with checks"},
]


@pytest.mark.parametrize("options", OPTIONS, ids=json.dumps)
def test_the_json_is_the_models_json(state: ServiceState, scene: tuple, options: dict) -> None:
    jpeg, annotations, names = scene
    request = {
        "instances": [{"object": n, "bbox": a["bbox"]} for a, n in zip(annotations, names, strict=True)],
        **options,
    }
    if "pose" in options:
        checks = [
            {"instance": i, "rotation": a["cam_R_m2c"], "translation": a["cam_t_m2c"]}
            for i, a in enumerate(annotations)
        ]
        request["pose"] = {"K": annotations[0]["cam_K"], "check": checks}
    query = predict_query(PredictParameters.model_validate(request))
    manifest = state.detector.manifest
    prediction = state.predictor.predict(jpeg, query)

    body = predict_body(prediction, query, manifest)
    written = predict_json(prediction, query, manifest)

    assert written == PredictResponse.model_validate(body).model_dump_json().encode()
    assert written == predict_response(prediction, query, manifest).model_dump_json().encode()
    answer = json.loads(written)
    keypoints = [kp for instance in answer["instances"] for kp in instance["keypoints"]]
    assert len(answer["instances"]) == len(annotations) and keypoints
    if options.get("epsilon") == 0.001:
        assert {kp["set"]["type"] for kp in keypoints} == {"unbounded"}
    if "stratify" in options:
        assert all("stratum" in kp["guarantee"] for kp in keypoints)
    else:
        assert not any("stratum" in kp["guarantee"] for kp in keypoints)
    assert all(("pose" in instance) == ("pose" in options) for instance in answer["instances"])
    assert all((kp["statistics"] is not None) == bool(options.get("include_statistics")) for kp in keypoints)
