"""The keypoint-service command line (its main, in this process): predict (JSON and PNG, through the
client, serving the model itself or asking a running service) and offline calibrate."""

from __future__ import annotations

import json
import subprocess
from pathlib import Path

import cv2
import numpy as np

from calibration_store import open_store
from service.api.predict.predict_schemas import PoseOut
from service.detector.session import file_sha256
from tests.api.in_process import OnLoopback
from tests.cli_calls import run as run_main
from tests.live.server import free_port
from tests.predict_client import predict_json
from tests.samples import Sample, count_instances, samples_by_image


def run(args: list[str], data_dir: Path, expect: int = 0) -> subprocess.CompletedProcess:
    result = run_main(args, data_dir)
    assert result.returncode == expect, (
        f"exit {result.returncode}\nstdout:\n{result.stdout}\nstderr:\n{result.stderr}"
    )
    return result


def predict_args(path: Path, group: list[Sample], *options: str) -> tuple[list[str], dict]:
    """The command line's arguments, and the same request as POST /v1/predict takes it."""
    boxes = [(s.object, ",".join(f"{v:g}" for v in s.bbox)) for s in group]
    args = ["predict", str(path), *options]
    for name, box in boxes:
        args += ["--instance", f"{name}:{box}"]
    instances = [{"object": name, "bbox": [float(v) for v in box.split(",")]} for name, box in boxes]
    return args, {"instances": instances}


def services_answers(server: OnLoopback, path: Path, parameters: dict) -> tuple[dict, bytes]:
    """The service's JSON answer, and the PNG it draws."""
    image = path.read_bytes()
    answer = predict_json(server.client, image, parameters)
    drawn = predict_json(server.client, image, parameters, headers={"Accept": "image/png"})
    assert answer.status_code == drawn.status_code == 200, answer.text
    return answer.json(), drawn.content


def printed_answer(printed: str) -> dict:
    """What the command line printed: the client's result, members in the document's order."""
    answer = json.loads(printed)
    assert list(answer) == sorted(answer) and printed.endswith("}\n")
    return answer


def test_predict_prints_json_and_writes_a_png(
    tmp_path: Path, samples: list[Sample], server: OnLoopback
) -> None:
    path, group = next(iter(samples_by_image(samples).items()))
    args, parameters = predict_args(path, group, "--png", str(tmp_path / "out.png"), "--nonconformity", "var")
    printed = run(args, tmp_path / "data").stdout
    body = json.loads(printed)

    image = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    assert body["image"] == {"width": image.shape[1], "height": image.shape[0]}
    assert body["calibration"]["version"] == 1 and body["calibration"]["nonconformity"] == "var"
    assert [i["object"] for i in body["instances"]] == [s.object for s in group]
    for instance in body["instances"]:
        for keypoint in instance["keypoints"]:
            assert keypoint["set"]["type"] in ("ball", "unbounded")

    drawn = cv2.imread(str(tmp_path / "out.png"), cv2.IMREAD_COLOR)
    assert drawn is not None and drawn.shape[:2] == image.shape[:2]
    assert (tmp_path / "out.png").read_bytes().startswith(b"\x89PNG")
    assert np.any(drawn != cv2.imread(str(path), cv2.IMREAD_COLOR))
    # The service's answer and drawing.
    assert (printed_answer(printed), (tmp_path / "out.png").read_bytes()) == services_answers(
        server, path, {**parameters, "nonconformity": "var"}
    )


def test_predict_asks_a_running_service(tmp_path: Path, samples: list[Sample], server: OnLoopback) -> None:
    path, group = list(samples_by_image(samples).items())[1]
    args, parameters = predict_args(path, group, "--url", server.url, "--png", str(tmp_path / "out.png"))
    printed = run(args, tmp_path / "data").stdout
    assert (printed_answer(printed), (tmp_path / "out.png").read_bytes()) == services_answers(
        server, path, parameters
    )

    unknown = run(
        ["predict", str(path), "--url", server.url, "--instance", "nothing:1,1,9,9"], tmp_path, expect=2
    )
    assert "instances[0].object: 'nothing' is not an object" in unknown.stderr
    assert "Traceback" not in unknown.stderr
    closed = f"http://127.0.0.1:{free_port()}"
    unreachable = run(
        ["predict", str(path), "--url", closed, "--instance", "duck:1,1,9,9"], tmp_path, expect=1
    )
    assert (
        f"error: {closed}/v1/predict: ConnectError" in unreachable.stderr
        and "Traceback" not in unreachable.stderr
    )


def test_predict_prints_and_draws_the_pose(
    tmp_path: Path, samples: list[Sample], server: OnLoopback, coco: dict
) -> None:
    path, group = next(iter(samples_by_image(samples).items()))
    camera = coco["annotations"][0]["cam_K"]  # one camera renders every sample
    (fx, _, cx), (_, fy, cy), _ = camera
    intrinsics = ",".join(f"{v:g}" for v in (fx, fy, cx, cy))
    png = tmp_path / "pose.png"
    args, parameters = predict_args(
        path, group, "--url", server.url, "--coverage", "object", "--pose-k", intrinsics, "--png", str(png)
    )
    printed = run(args, tmp_path / "data").stdout
    parameters |= {"coverage": "object"}
    answer, drawn = services_answers(server, path, parameters | {"pose": {"K": camera}})
    assert (printed_answer(printed), png.read_bytes()) == (answer, drawn)
    poses = [instance["pose"] for instance in json.loads(printed)["instances"]]
    assert len(poses) == len(group) and all(set(pose) == set(PoseOut.model_fields) for pose in poses)
    assert drawn != services_answers(server, path, parameters)[1], "the PNG draws the poses"
    # The matrix as JSON asks the same.
    args[args.index(intrinsics)] = json.dumps(camera)
    assert run(args, tmp_path / "data").stdout == printed

    def refused(*options: str) -> str:
        result = run(
            ["predict", str(path), "--instance", "duck:1,1,9,9", *options], tmp_path / "data", expect=2
        )
        assert "Traceback" not in result.stderr
        return result.stderr

    assert "--pose-k needs --coverage object" in refused("--pose-k", intrinsics)
    assert "use fx,fy,cx,cy" in refused("--coverage", "object", "--pose-k", "572,572,320")
    skewed = json.dumps([[fx, 2.0, cx], [0, fy, cy], [0, 0, 1]])
    assert "error: --pose-k: K[0][1] (skew)" in refused("--coverage", "object", "--pose-k", skewed)


def test_calibrate_creates_and_activates_a_version(
    tmp_path: Path, samples_dir: Path, coco: dict, model_path: Path
) -> None:
    data = tmp_path / "data"
    data.mkdir()
    total = count_instances(coco)
    model_hash = file_sha256(model_path / "model.onnx")
    store_url = f"sqlite:///{data / 'calibrations.db'}"

    # 52 instances: every keypoint's n is below the floor, so the guardrails refuse to activate
    refused = run(["calibrate", str(samples_dir), "--activate", "--note", "from the CLI"], data)
    summary = json.loads(refused.stdout)
    assert (summary["version"], summary["instances"], summary["activated"]) == (1, total, False)
    assert "guardrail: keypoint" in refused.stderr and "--force --reason" in refused.stderr
    with open_store(store_url) as store:
        assert store.active_version(model_hash) is None

    # The same batch again is a copy of version 1: refused unless asked for (--allow-duplicate)
    again = run(["calibrate", str(samples_dir)], data, expect=2)
    assert "equal to calibration version 1" in again.stderr
    forced = run(
        [
            "calibrate",
            str(samples_dir),
            "--activate",
            "--force",
            "--allow-duplicate",
            "--reason",
            "a test batch",
        ],
        data,
    )
    assert json.loads(forced.stdout)["activated"] is True
    with open_store(store_url) as store:
        info = store.get_version(model_hash, 2)
        assert (info.number, info.n_instances, info.author) == (2, total, "cli")
        activation = store.active_version(model_hash)
        assert (activation.version, activation.reason) == (2, "a test batch")
        outcomes = [(e.action, e.outcome) for e in store.audit_log(model_hash)]
        assert outcomes[:2] == [("activation", "forced"), ("calibration", "stored")]

    # the same batch appended to a version that holds it: refused, nothing stored
    repeated = run(["calibrate", str(samples_dir), "--append-to", "2"], data, expect=2)
    assert f"{total} of {total} instances are already counted" in repeated.stderr
    assert "Traceback" not in repeated.stderr
    with open_store(store_url) as store:
        assert [v.number for v in store.list_versions(model_hash)] == [1, 2]


def test_calibrate_force_needs_a_reason(tmp_path: Path, samples_dir: Path) -> None:
    result = run(["calibrate", str(samples_dir), "--activate", "--force"], tmp_path / "data", expect=2)
    assert "force needs a reason" in result.stderr and "Traceback" not in result.stderr
