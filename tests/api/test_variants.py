"""Model variants: `keypoint-service optimize` writes a whole model folder that serves like any other,
the bundled int8 variant serves the README request through one setting, answers name the variant,
and a calibration of one variant is never served with another."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pytest

from service.calibration.bundle import BUNDLE_FILENAME
from service.detector.compression import convert_float16
from service.detector.manifest import MANIFEST_FILENAME, MODEL_FILENAME
from service.detector.session import Detector, ModelMismatch, file_sha256
from service.infra.settings import PACKAGE_ROOT
from tests.api.in_process import InProcess
from tests.cli_calls import assert_one_line_error, run
from tests.samples import model_dir
from tests.service_calls import ADMIN_TOKEN

SOURCE = PACKAGE_ROOT / "models" / "lmo-synth-unet"
BUNDLED_INT8 = PACKAGE_ROOT / "models" / "lmo-synth-unet-int8"
SAMPLES = SOURCE / "samples"
README_IMAGE = SAMPLES / "images" / "000000.jpg"
README_REQUEST = {
    "instances": [{"object": "duck", "bbox": [235, 217, 67, 64]}],
    "epsilon": 0.1,
    "nonconformity": "cov",
}


def predict(service: InProcess, **options: object) -> dict:
    request = {**README_REQUEST, **options}
    files = {"image": README_IMAGE.read_bytes()}
    response = service.client.post("/v1/predict", files=files, data={"request": json.dumps(request)})
    assert response.status_code == 200, response.text
    return response.json()


def bundle_counts(folder: Path) -> dict[str, int]:
    with np.load(folder / BUNDLE_FILENAME) as data:
        return {key.split("/")[0]: len(data[key]) for key in data.files if key.endswith("/refs")}


@pytest.fixture(scope="module")
def optimized(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """The samples' int8 variant: 4 images set the ranges, the other 8 calibrate."""
    out = tmp_path_factory.mktemp("variant") / "int8"
    args = ["optimize", str(SOURCE), str(SAMPLES), "--out", str(out), "--range-images", "4"]
    result = run(args, tmp_path_factory.mktemp("optimize-data"))
    assert result.returncode == 0, result.stderr
    summary = json.loads(result.stdout)
    assert summary["variant"]["name"] == "int8" and summary["model_dir"] == str(out)
    return out


def test_optimize_writes_a_whole_model_folder_calibrated_with_the_new_model(optimized: Path) -> None:
    manifest = json.loads((optimized / MANIFEST_FILENAME).read_text())
    variant = manifest.pop("variant")
    source = json.loads((SOURCE / MANIFEST_FILENAME).read_text())
    assert manifest == source  # the same contract: crops, heatmaps, keypoints
    assert variant["source_name"] == source["name"]
    assert variant["source_sha256"] == file_sha256(SOURCE / MODEL_FILENAME)
    assert variant["model_sha256"] == file_sha256(optimized / MODEL_FILENAME) != variant["source_sha256"]
    assert variant["ranges"].startswith("4 images of samples")
    with np.load(optimized / BUNDLE_FILENAME) as data:
        metadata = json.loads(str(data["metadata"]))
        refs = {ref for key in data.files if key.endswith("/refs") for ref in data[key]}
    assert metadata["model_hash"] == variant["model_sha256"]
    images = {ref.split(":")[1] for ref in refs}
    samples = json.loads((SAMPLES / "annotations.json").read_text())
    assert len(images) == len(samples["images"]) - 4  # the range images are kept out of the calibration
    assert Detector(optimized).manifest.variant_name == "int8"


def test_an_optimized_folder_serves_like_any_other(optimized: Path, tmp_path: Path) -> None:
    with InProcess(tmp_path / "data", model_dir=optimized) as service:
        answer = predict(service)
    guarantee = answer["instances"][0]["keypoints"][0]["guarantee"]
    assert answer["model"]["variant"] == guarantee["model_variant"] == "int8"
    assert guarantee["n"] == bundle_counts(optimized)["duck"]


def test_the_bundled_variant_serves_the_readme_request_through_one_setting(tmp_path: Path) -> None:
    with InProcess(tmp_path / "data", model_dir=BUNDLED_INT8) as service:
        answer = predict(service)
        model = service.client.get("/v1/model").json()
    keypoints = answer["instances"][0]["keypoints"]
    assert len(keypoints) == 8 and all(k["set"]["type"] == "ellipse" for k in keypoints)
    assert {k["guarantee"]["model_variant"] for k in keypoints} == {"int8"}
    assert {k["guarantee"]["n"] for k in keypoints} == {bundle_counts(BUNDLED_INT8)["duck"]}
    assert min(bundle_counts(BUNDLED_INT8).values()) >= 2000
    assert model["variant"] == "int8" and model["hash"] == file_sha256(BUNDLED_INT8 / MODEL_FILENAME)
    assert model["manifest"]["variant"]["source_sha256"] == file_sha256(SOURCE / MODEL_FILENAME)


def test_the_default_model_is_named_original(api: InProcess) -> None:
    answer = predict(api)
    assert answer["model"]["variant"] == answer["instances"][0]["keypoints"][0]["guarantee"]["model_variant"]
    assert api.client.get("/v1/model").json()["variant"] == "original" == answer["model"]["variant"]
    assert "variant" not in api.client.get("/v1/model").json()["manifest"]


def test_variants_on_one_store_each_serve_their_own_calibration(tmp_path: Path) -> None:
    data = tmp_path / "data"
    with InProcess(data, model_dir=model_dir()) as original:
        n_original = predict(original)["instances"][0]["keypoints"][0]["guarantee"]["n"]
    with InProcess(data, model_dir=BUNDLED_INT8, admin_token=ADMIN_TOKEN) as fast:
        answer = predict(fast)
        versions = fast.client.get("/v1/admin/calibrations", headers=fast.admin).json()
        unknown = fast.client.post(
            "/v1/predict",
            files={"image": README_IMAGE.read_bytes()},
            data={"request": json.dumps({**README_REQUEST, "calibration_version": 2})},
        )
    assert answer["instances"][0]["keypoints"][0]["guarantee"]["n"] == bundle_counts(BUNDLED_INT8)["duck"]
    assert n_original == bundle_counts(SOURCE)["duck"]
    assert [v["version"] for v in versions["versions"]] == [1] and versions["model_hash"] == answer["model"][
        "hash"
    ]
    assert unknown.status_code == 404, unknown.text


def test_a_calibration_of_another_variant_in_the_folder_is_not_served(tmp_path: Path) -> None:
    folder = tmp_path / "int8"
    shutil.copytree(BUNDLED_INT8, folder)
    shutil.copyfile(SOURCE / BUNDLE_FILENAME, folder / BUNDLE_FILENAME)  # float32's scores
    with InProcess(tmp_path / "data", model_dir=folder) as service:
        refused = service.client.post(
            "/v1/predict",
            files={"image": README_IMAGE.read_bytes()},
            data={"request": json.dumps(README_REQUEST)},
        )
        logged = service.log()
    assert refused.status_code == 503, refused.text
    assert "computed for another model" in logged


def test_a_variant_folder_with_another_model_file_is_refused(tmp_path: Path) -> None:
    folder = tmp_path / "int8"
    shutil.copytree(BUNDLED_INT8, folder)
    shutil.copyfile(SOURCE / MODEL_FILENAME, folder / MODEL_FILENAME)
    with pytest.raises(ModelMismatch, match="names the int8 variant of model.onnx"):
        Detector(folder)


@pytest.mark.parametrize(
    ("args", "fragment"),
    [
        (["--precision", "float16"], "float16 is for GPUs"),
        (["--range-images", "12"], "--range-images 12 must be at least 1 and leave the others"),
    ],
)
def test_optimize_refuses_what_cannot_make_a_variant(args: list[str], fragment: str, tmp_path: Path) -> None:
    result = run(["optimize", str(SOURCE), str(SAMPLES), "--out", str(tmp_path / "out"), *args], tmp_path)
    assert_one_line_error(result, 2, fragment)


def test_optimize_refuses_a_variant_and_a_folder_in_use(tmp_path: Path) -> None:
    again = run(["optimize", str(BUNDLED_INT8), str(SAMPLES), "--out", str(tmp_path / "out")], tmp_path)
    assert_one_line_error(again, 2, "is already the int8 variant")
    busy = run(["optimize", str(SOURCE), str(SAMPLES), "--out", str(SOURCE)], tmp_path)
    assert_one_line_error(busy, 2, "is not empty")


def test_float16_conversion_keeps_the_manifests_float32_tensors(tmp_path: Path) -> None:
    import onnx
    import onnxruntime as ort

    converted = tmp_path / MODEL_FILENAME
    convert_float16(SOURCE / MODEL_FILENAME, converted)
    graph = onnx.load(str(converted)).graph
    float32, float16 = onnx.TensorProto.FLOAT, onnx.TensorProto.FLOAT16
    assert {t.type.tensor_type.elem_type for t in [*graph.input, *graph.output]} == {float32}
    assert {t.data_type for t in graph.initializer} == {float16}
    crops = np.random.default_rng(0).normal(size=(2, 3, 128, 128)).astype(np.float32)
    ran = [
        ort.InferenceSession(str(p)).run(None, {"image": crops})[0]
        for p in (SOURCE / MODEL_FILENAME, converted)
    ]
    assert np.abs(ran[1] - ran[0]).max() < 0.02 * np.abs(ran[0]).max()  # float16's 11 bits, through 20 layers


def test_a_failed_optimize_leaves_no_model_folder(tmp_path: Path) -> None:
    batch = tmp_path / "batch"
    shutil.copytree(SAMPLES, batch)
    images = sorted(json.loads((batch / "annotations.json").read_text())["images"], key=lambda i: i["id"])
    damaged = batch / images[1]["file_name"]  # not one of the 4 range images (0, 4, 7, 11 of 12)
    damaged.write_bytes(damaged.read_bytes()[: damaged.stat().st_size // 2])  # its header still reads
    out = tmp_path / "models" / "int8"
    result = run(["optimize", str(SOURCE), str(batch), "--out", str(out), "--range-images", "4"], tmp_path)
    assert result.returncode == 2, result.stderr
    assert "rejected" in result.stderr and "cannot be decoded" in result.stderr
    assert list((tmp_path / "models").iterdir()) == []  # neither the folder nor its staging copy
