"""The client installed alone into a fresh virtual environment, from the checkout, which keeps no
build output: pip brings httpx and pydantic and nothing of the server; it predicts against a
real server without numpy; with its numpy extra, its contains() agrees with the server's own
set geometry on the bundled samples' labelled keypoints and on points scattered around every set."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path
from typing import Any

import numpy as np

from service.conformal.geometry import ball_shapes, contains
from tests.live.client.conftest import CLIENT_ROOT
from tests.live.server import LiveServer
from tests.predict_client import instances_of, predict_json
from tests.samples import Sample, samples_by_image

SERVER_ONLY = {
    "conformal-keypoint-service",
    "onnxruntime",
    "opencv-python-headless",
    "simplejpeg",
    "fastapi",
    "starlette",
    "uvicorn",
    "python-multipart",
    "prometheus-client",
    "pydantic-settings",
    "numpy",
}
SCATTERED = 40  # points around each set, besides its labelled keypoint

# Runs inside the fresh environment, from an empty folder: argv[1] says what to ask, argv[2]
# receives the answers.
SCRIPT = """
import importlib.util, json, sys
from pathlib import Path
from keypoint_client import KeypointClient

job = json.loads(Path(sys.argv[1]).read_text())
answer = {"importable": {name: importlib.util.find_spec(name) is not None for name in ("service", "numpy")},
          "results": [], "contains": [], "refusal": None}
with KeypointClient(job["url"]) as client:
    for item in job["items"]:
        image = item["path"] if item["by"] == "path" else Path(item["path"]).read_bytes()
        result = client.predict(image, item["instances"], epsilon=item["epsilon"],
                                nonconformity=item["nonconformity"])
        answer["results"].append(result.to_dict())
        keypoints = [k for instance in result.instances for k in instance.keypoints]
        try:
            answer["contains"].append([k.set.contains(points).tolist()
                                       for k, points in zip(keypoints, item["probes"])])
        except ImportError as error:
            answer["refusal"] = str(error)
Path(sys.argv[2]).write_text(json.dumps(answer))
"""


def run(*command: str | Path, cwd: Path) -> str:
    result = subprocess.run(list(map(str, command)), cwd=cwd, capture_output=True, text=True, timeout=600)
    assert result.returncode == 0, f"{command}: exit {result.returncode}\n{result.stdout}\n{result.stderr}"
    return result.stdout


def files(folder: Path) -> set[Path]:
    return {path for path in folder.rglob("*") if "__pycache__" not in path.parts}


def python_says(python: Path, expression: str, cwd: Path) -> Any:
    """The JSON value of ``expression`` evaluated by ``python``."""
    code = f"import importlib.metadata, importlib.util, json, pathlib; print(json.dumps({expression}))"
    return json.loads(run(python, "-c", code, cwd=cwd))


def installed(python: Path, cwd: Path) -> set[str]:
    names = python_says(python, "[d.metadata['Name'] for d in importlib.metadata.distributions()]", cwd)
    return {name.lower().replace("_", "-") for name in names}


def server_sets(result: dict) -> tuple[np.ndarray, np.ndarray]:
    """Every keypoint's set as the service's geometry writes it: centres and shape matrices."""
    centers, shapes = [], []
    for keypoint in (k for instance in result["instances"] for k in instance["keypoints"]):
        region = keypoint["set"]
        centers.append(keypoint["point"])
        if region["type"] == "ball":
            shapes.append(ball_shapes(np.array([region["radius"]]))[0])
        else:
            shapes.append(np.array(region.get("shape_matrix", np.zeros((2, 2)))))
    return np.array(centers), np.array(shapes)


def probes(result: dict, group: list[Sample], rng: np.random.Generator) -> list[list[list[float]]]:
    """Per keypoint: its labelled position (when labelled), then points scattered around its set."""
    centers, shapes = server_sets(result)
    labels = [keypoint for sample in group for keypoint in sample.keypoints]
    points = []
    for (x, y, v), center, shape in zip(labels, centers, shapes, strict=True):
        scale = 3.0 / np.sqrt(np.linalg.eigvalsh(shape).min()) if shape.any() else 20.0
        scatter = center + rng.normal(0.0, scale, (SCATTERED, 2))
        points.append([[x, y]] * (v > 0) + scatter.tolist())
    return points


def questions(server: LiveServer, samples: list[Sample]) -> tuple[list[dict], list[dict]]:
    """Every sample image with each function (as a path or as bytes), and one with unbounded
    sets; with the service's own answers."""
    groups = list(samples_by_image(samples).items())
    asked = [(index, function, 0.1) for index in range(len(groups)) for function in ("peak", "var", "cov")]
    asked.append((0, "cov", 0.0001))  # t = floor((n + 1) * 0.0001) = 0: unbounded sets
    rng = np.random.default_rng(18)
    items, expected = [], []
    for index, function, epsilon in asked:
        path, group = groups[index]
        parameters = {"instances": instances_of(group), "epsilon": epsilon, "nonconformity": function}
        expected.append(predict_json(server.client, path.read_bytes(), parameters).json())
        item = {"path": str(path), "by": "bytes" if index % 2 else "path", **parameters}
        items.append({**item, "probes": probes(expected[-1], group, rng)})
    return items, expected


def test_the_client_alone_predicts_and_agrees_with_the_server(
    server: LiveServer, samples: list[Sample], tmp_path: Path
) -> None:
    run(sys.executable, "-m", "venv", tmp_path / "venv", cwd=tmp_path)
    python = tmp_path / "venv" / "bin" / "python"
    pip = (python, "-m", "pip", "install", "--quiet", "--disable-pip-version-check")
    checkout = files(CLIENT_ROOT)
    run(*pip, CLIENT_ROOT, cwd=tmp_path)
    assert files(CLIENT_ROOT) == checkout, "the install left files in the checkout"

    alone = installed(python, tmp_path)
    assert {"keypoint-client", "httpx", "pydantic"} <= alone and not alone & SERVER_ONLY, sorted(alone)
    requires = python_says(python, "importlib.metadata.requires('keypoint-client')", tmp_path)
    assert sorted({r.split(">")[0] for r in requires}) == ["httpx", "numpy", "pydantic", "simplejpeg"], (
        requires
    )
    extras = [r for r in requires if r.startswith(("numpy", "simplejpeg"))]
    assert all('; extra == "' in r for r in extras), requires  # numpy and simplejpeg only as extras
    origin = "importlib.util.find_spec('keypoint_client').origin"
    package = python_says(python, f"str(pathlib.Path({origin}).parent)", tmp_path)
    assert (Path(package) / "py.typed").is_file() and tmp_path / "venv" in Path(package).parents

    items, expected = questions(server, samples)
    (tmp_path / "script.py").write_text(SCRIPT)
    (tmp_path / "job.json").write_text(json.dumps({"url": server.url, "items": items}))

    # Without numpy: it predicts; the geometry says what to install.
    run(python, "script.py", "job.json", "answer.json", cwd=tmp_path)
    answer = json.loads((tmp_path / "answer.json").read_text())
    assert answer["importable"] == {"service": False, "numpy": False}
    assert answer["results"] == expected
    assert "pip install './client[numpy]' from the service's checkout" in answer["refusal"]

    # With the numpy extra: contains() is the server's geometry.
    run(*pip, f"{CLIENT_ROOT}[numpy]", cwd=tmp_path)
    assert installed(python, tmp_path) - alone == {"numpy"}
    run(python, "script.py", "job.json", "answer.json", cwd=tmp_path)
    answer = json.loads((tmp_path / "answer.json").read_text())
    assert answer["results"] == expected and answer["refusal"] is None
    kinds, verdicts = set(), []
    for result, item, answered in zip(expected, items, answer["contains"], strict=True):
        centers, shapes = server_sets(result)
        for center, shape, points, said in zip(centers, shapes, item["probes"], answered, strict=True):
            many = len(points)
            truth = contains(
                np.array(points), np.repeat(center[None], many, 0), np.repeat(shape[None], many, 0)
            )
            assert said == truth.tolist(), (item["nonconformity"], center, shape)
            verdicts += said
        kinds |= {k["set"]["type"] for instance in result["instances"] for k in instance["keypoints"]}
    assert kinds == {"ball", "ellipse", "unbounded"} and True in verdicts and False in verdicts
