"""keypoint-service evaluate: the paper's evaluation of a version on a labeled folder, as
Markdown with PNG figures, checked against coverage recomputed from the service's answers."""

from __future__ import annotations

import json
import re
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from scipy import stats

from service import cli as service_cli
from tests.api.in_process import OnLoopback
from tests.cli_calls import run
from tests.live.server import service_env
from tests.predict_client import contains, predict_ok
from tests.samples import Sample, samples_by_image

KINDS = ("peak", "var", "cov")
EPSILONS = (0.1, 0.2)
FIGURES = ("validity.png", "bands.png", "tightness.png", "adaptiveness.png")


def evaluate(data_dir: Path, *args: str, expect: int = 0) -> subprocess.CompletedProcess:
    """``keypoint-service evaluate ARGS`` (its main, in this process), with the status expected."""
    result = run(["evaluate", *args], data_dir)
    assert result.returncode == expect, f"exit {result.returncode}\n{result.stdout}\n{result.stderr}"
    return result


@pytest.fixture(scope="module")
def report(server: OnLoopback, samples_dir: Path, tmp_path_factory: pytest.TempPathFactory) -> Path:
    """The report on the bundled samples against the server's store (bundled calibration, version 1)."""
    out = tmp_path_factory.mktemp("evaluation")
    options = [f"--epsilon={e}" for e in EPSILONS]
    result = evaluate(server.data_dir, str(samples_dir), "--version", "1", "--out", str(out), *options)
    assert f"wrote {out / 'evaluation.md'} (version 1, " in result.stdout
    return out


def table_rows(text: str, heading: str) -> list[list[str]]:
    """The cells of the first table after ``heading``."""
    section = text[text.index(heading) :]
    lines = section[section.index("\n|") + 1 :].split("\n\n")[0].splitlines()
    return [[cell.strip() for cell in line.strip("|").split("|")] for line in lines[2:]]


def served_coverage(server: OnLoopback, samples: list[Sample], kind: str, epsilon: float, scope: str):
    """Per group (keypoint, or object for the object scope): covered count, count, and the
    guarantee's n and t, from the sets POST /v1/predict answers."""
    counts: dict[str, list[int]] = {}
    for path, group in samples_by_image(samples).items():
        parameters = {
            "instances": [{"object": s.object, "bbox": s.bbox} for s in group],
            "epsilon": epsilon,
            "nonconformity": kind,
            "coverage": scope,
            "calibration_version": 1,
        }
        answer = predict_ok(server.client, path.read_bytes(), parameters)
        for sample, instance in zip(group, answer["instances"], strict=True):
            inside = [
                contains(k["set"], (x, y))
                for k, (x, y, v) in zip(instance["keypoints"], sample.keypoints, strict=True)
                if v > 0
            ]
            guarantee = instance["keypoints"][0]["guarantee"]
            if scope == "object":
                if len(inside) == len(sample.keypoints):
                    _count(counts, sample.object, all(inside), 1, guarantee)
                continue
            for keypoint, (x, y, v) in zip(instance["keypoints"], sample.keypoints, strict=True):
                if v > 0:
                    covered = contains(keypoint["set"], (x, y))
                    _count(counts, keypoint["name"], covered, 1, keypoint["guarantee"])
    return counts


def _count(counts: dict, name: str, covered: bool, m: int, guarantee: dict) -> None:
    entry = counts.setdefault(name, [0, 0, guarantee["n"], guarantee["t"]])
    entry[0] += int(covered)
    entry[1] += m


def inside_band(covered: int, m: int, n: int, t: int) -> bool:
    """The central 95% interval of BetaBinomial(m, n+1-t, t), from scipy (not the service's laws)."""
    low, high = stats.betabinom.ppf([0.025, 0.975], m, n + 1 - t, t)
    return low <= covered <= high


def test_writes_markdown_and_figures(report: Path) -> None:
    text = (report / "evaluation.md").read_text()
    assert "    keypoint-service evaluate " in text and "--version 1" in text  # the command that made it
    for figure in FIGURES:
        path = report / "figures" / figure
        assert path.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n" and path.stat().st_size < 1_500_000
        assert f"](figures/{figure})" in text
    for section in (
        "## Validity",
        "### Object scope",
        "### Per keypoint against the band",
        "## Tightness",
        "## Adaptiveness",
    ):
        assert section in text
    assert "n/a" not in text


@pytest.mark.parametrize("scope", ["keypoint", "object"])
def test_coverage_agrees_with_the_served_sets(
    report: Path, server: OnLoopback, samples: list[Sample], scope: str
) -> None:
    text = (report / "evaluation.md").read_text()
    heading = "## Validity" if scope == "keypoint" else "### Object scope"
    table = {(row[0], float(row[1])): row for row in table_rows(text, heading)}
    bands = {(row[0], row[1]): row for row in table_rows(text, "### Per keypoint against the band")}
    for kind in KINDS:
        for epsilon in EPSILONS:
            counts = served_coverage(server, samples, kind, epsilon, scope)
            coverage = np.array([covered / m for covered, m, _, _ in counts.values()])
            inside = np.mean([inside_band(*entry) for entry in counts.values()])
            row = table[(kind, epsilon)]
            offset = 3 if scope == "keypoint" else 2  # keypoint rows also give 1-eps
            assert row[offset : offset + 3] == [
                f"{coverage.mean():.3f}",
                f"{coverage.min():.3f}",
                f"{inside:.3f}",
            ], (kind, epsilon)
            if epsilon == 0.1:
                outside = sum(not inside_band(*entry) for entry in counts.values())
                assert bands[(kind, scope)][3] == f"{outside} of {len(counts)}"


def test_adaptiveness_counts_the_visibility_flags(report: Path, samples: list[Sample]) -> None:
    text = (report / "evaluation.md").read_text()
    flags = [v for sample in samples for _, _, v in sample.keypoints]
    assert f"visible (n={flags.count(2)})" in text and f"occluded (n={flags.count(1)})" in text


def test_the_active_version_is_the_default(server: OnLoopback, samples_dir: Path, tmp_path: Path) -> None:
    result = evaluate(server.data_dir, str(samples_dir), "--out", str(tmp_path), "--epsilon", "0.1")
    assert "(version 1, 52 instances)" in result.stdout
    assert (tmp_path / "figures" / "bands.png").is_file()


def refusal(data_dir: Path, *args: str, details: bool = False) -> str:
    """The one-line message of exit status 2 (then, with ``details``, the list of every problem
    found in a file, as ``calibrate`` prints it)."""
    result = evaluate(data_dir, *args, expect=2)
    first, *rest = result.stderr.strip().splitlines()
    assert first.startswith("error: ") and (
        all(line.startswith("  ") for line in rest) if details else not rest
    ), result.stderr
    return first


def test_refuses_a_missing_folder(tmp_path: Path) -> None:
    message = refusal(tmp_path / "data", str(tmp_path / "nowhere"), "--out", str(tmp_path / "out"))
    assert "nowhere is not a folder" in message
    assert not (tmp_path / "out").exists()


def test_refuses_a_folder_that_is_not_coco(tmp_path: Path) -> None:
    folder = tmp_path / "photos"
    folder.mkdir()
    (folder / "a.jpg").write_bytes(b"\xff\xd8\xff")
    message = refusal(tmp_path / "data", str(folder), "--out", str(tmp_path / "out"))
    assert "annotations.json" in message
    (folder / "annotations.json").write_text(json.dumps({"images": "no"}))
    message = refusal(tmp_path / "data", str(folder), "--out", str(tmp_path / "out"), details=True)
    assert "annotations.json has 3 problem(s); first: images: must be a list" in message
    assert not (tmp_path / "out").exists()


def test_refuses_an_unknown_version(server: OnLoopback, samples_dir: Path, tmp_path: Path) -> None:
    message = refusal(server.data_dir, str(samples_dir), "--version", "99", "--out", str(tmp_path / "out"))
    assert "calibration version 99 does not exist" in message and "versions: 1" in message
    assert not (tmp_path / "out").exists()


def test_refuses_without_matplotlib(
    samples_dir: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture
) -> None:
    monkeypatch.setitem(sys.modules, "matplotlib", None)  # import matplotlib raises ImportError
    for name, value in service_env(tmp_path / "data").items():
        monkeypatch.setenv(name, value)
    status = service_cli.main(["evaluate", str(samples_dir), "--out", str(tmp_path / "out")])
    error = capsys.readouterr().err
    assert status == 2 and error.count("\n") == 1
    assert "matplotlib, which is not installed" in error and "[evaluate]" in error
    assert not (tmp_path / "data").exists()  # refused before the model and the store were opened


def one_object_without_occlusion_flags(samples_dir: Path, coco: dict, folder: Path, name: str) -> int:
    """The samples' instances of one object, every labeled keypoint marked visible (v = 2) and
    without visib_fract: a batch whose labels cannot tell occluded from visible."""
    names = {c["id"]: c["name"] for c in coco["categories"]}
    annotations = [dict(a) for a in coco["annotations"] if names[a["category_id"]] == name]
    for annotation in annotations:
        flat = annotation["keypoints"]
        annotation["keypoints"] = [2 if i % 3 == 2 and v == 1 else v for i, v in enumerate(flat)]
        annotation.pop("visib_fract", None)
    used = {a["image_id"] for a in annotations}
    images = [image for image in coco["images"] if image["id"] in used]
    for image in images:
        (folder / image["file_name"]).parent.mkdir(parents=True, exist_ok=True)
        (folder / image["file_name"]).write_bytes((samples_dir / image["file_name"]).read_bytes())
    document = {**coco, "images": images, "annotations": annotations}
    (folder / "annotations.json").write_text(json.dumps(document))
    return len(annotations)


def test_a_batch_of_one_object_without_occlusion_flags(
    server: OnLoopback, samples_dir: Path, coco: dict, manifest: dict, tmp_path: Path
) -> None:
    duck = next(o for o in manifest["objects"] if o["name"] == "duck")
    count = one_object_without_occlusion_flags(samples_dir, coco, tmp_path / "duck", "duck")
    result = evaluate(
        server.data_dir,
        str(tmp_path / "duck"),
        "--out",
        str(tmp_path / "out"),
        "--epsilon",
        "0.0001",
        "--epsilon",
        "0.1",
    )
    assert f"(version 1, {count} instances)" in result.stdout
    text = (tmp_path / "out" / "evaluation.md").read_text()
    assert "Not measured: the labels of this batch do not carry both COCO visibility flags" in text
    assert not (tmp_path / "out" / "figures" / "adaptiveness.png").exists()
    assert "adaptiveness.png" not in text
    keypoints = len(duck["keypoints"])
    for kind in KINDS:  # the keypoints and the one object of the batch, not the model's
        assert re.search(rf"\| {kind} \| keypoint \| [0-9.]+ \| \d+ of {keypoints} \|", text)
        assert re.search(rf"\| {kind} \| object \| [0-9.]+ \| [01] of 1 \|", text)
    # eps 0.0001 needs 9,999 calibration scores: every set is the whole plane, and says so
    assert f"cov at eps 0.0001: {keypoints} of {keypoints}" in text
    assert "| 0.0001 | cov | a inf, b inf | inf | 0.000 |" in text
