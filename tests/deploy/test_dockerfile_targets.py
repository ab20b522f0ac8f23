"""The Dockerfile's targets, read statically (no registry here to pull the CUDA base from):
the default target is the CPU image and needs nothing of the CUDA stages; ``--target cuda``
swaps onnxruntime for onnxruntime-gpu and asks for the CUDA provider, as docs/operations.md says.
(tests/deploy/test_container.py builds and runs the default target.)"""

from __future__ import annotations

import re
import tomllib
from dataclasses import dataclass, field

import pytest

from service.infra.settings import PACKAGE_ROOT, Settings

DOCKERFILE = PACKAGE_ROOT / "Dockerfile"


@dataclass
class Stage:
    base: str
    name: str | None
    instructions: list[tuple[str, str]] = field(default_factory=list)  # (KEYWORD, arguments)

    def all(self, keyword: str) -> list[str]:
        return [arguments for kw, arguments in self.instructions if kw == keyword]

    def needs(self) -> set[str]:
        """Stages or images this one builds on: its base and every COPY --from."""
        copies = {m for args in self.all("COPY") for m in re.findall(r"--from=(\S+)", args)}
        return {self.base} | copies


def instructions(text: str) -> list[tuple[str, str]]:
    """(KEYWORD, arguments) per instruction, continuation lines joined, comments dropped."""
    lines = [line for line in text.splitlines() if not line.lstrip().startswith("#")]
    joined = re.sub(r"\\\n", " ", "\n".join(lines))
    return [(kw.upper(), args.strip()) for kw, args in re.findall(r"^(\w+)\s+(.*)$", joined, re.MULTILINE)]


def parse() -> tuple[dict[str, str], list[Stage]]:
    """The global ARG defaults and the stages, in order."""
    args: dict[str, str] = {}
    stages: list[Stage] = []
    for keyword, arguments in instructions(DOCKERFILE.read_text(encoding="utf-8")):
        if keyword == "FROM":
            base, _, name = arguments.partition(" AS ")
            stages.append(Stage(base.strip(), name.strip() or None))
        elif keyword == "ARG" and not stages:
            name, _, default = arguments.partition("=")
            args[name] = default
        else:
            stages[-1].instructions.append((keyword, arguments))
    return args, stages


def closure(stages: list[Stage], target: Stage) -> list[Stage]:
    """``target`` and every stage it needs, directly or not."""
    by_name = {stage.name: stage for stage in stages if stage.name}
    needed, frontier = [target], [target]
    while frontier:
        frontier = [by_name[n] for stage in frontier for n in stage.needs() if n in by_name]
        needed += [stage for stage in frontier if stage not in needed]
    return needed


def named(stages: list[Stage], name: str) -> Stage:
    return next(stage for stage in stages if stage.name == name)


def env(stage: Stage) -> dict[str, str]:
    return dict(re.findall(r"(\w+)=(\S+)", " ".join(stage.all("ENV"))))


@pytest.fixture(scope="module")
def dockerfile() -> tuple[dict[str, str], list[Stage]]:
    return parse()


def test_the_default_target_is_the_cpu_image_and_needs_no_cuda_stage(dockerfile) -> None:
    _, stages = dockerfile
    default = stages[-1]
    assert default.base == "python:3.11-slim-bookworm" and default.name is None
    needed = closure(stages, default)
    assert [stage.name for stage in needed] == [None, "build"]
    text = repr([stage.instructions for stage in needed])
    assert "onnxruntime-gpu" not in text and "EXECUTION_PROVIDERS" not in text and "cuda" not in text


def test_the_cuda_target_runs_onnxruntime_gpu_on_a_cuda_base(dockerfile) -> None:
    args, stages = dockerfile
    cuda = named(stages, "cuda")
    assert "${CUDA_IMAGE}" in {stage.base for stage in closure(stages, cuda)}
    assert re.fullmatch(r"nvidia/cuda:[\d.]+-cudnn-runtime-\S+", args["CUDA_IMAGE"])
    install = " ".join(cuda.all("RUN"))
    assert install.index("pip uninstall -y onnxruntime ") < install.index('--no-deps "onnxruntime-gpu')
    # a CUDA or cuDNN the provider was not built for fails the build, not the first start
    assert "libonnxruntime_providers_cuda.so" in install and '| grep "not found"' in install
    assert env(cuda)["CKS_EXECUTION_PROVIDERS"].startswith("CUDAExecutionProvider,")


def test_the_cuda_image_settings_are_valid_settings(dockerfile, monkeypatch) -> None:
    _, stages = dockerfile
    cuda_env = {k: v for k, v in env(named(stages, "cuda")).items() if k.startswith("CKS_")}
    unknown = [k for k in cuda_env if k.removeprefix("CKS_").lower() not in Settings.fields()]
    assert not unknown, f"the cuda stage sets settings the service does not read: {unknown}"
    for key, value in cuda_env.items():
        monkeypatch.setenv(key, value)
    assert Settings().model.execution_providers[0] == "CUDAExecutionProvider"


def test_both_images_run_the_same_way(dockerfile) -> None:
    _, stages = dockerfile
    cuda, default = named(stages, "cuda"), stages[-1]
    for keyword in ("USER", "VOLUME", "EXPOSE", "CMD", "WORKDIR"):
        assert cuda.all(keyword) == default.all(keyword), keyword
    shared = {k: v for k, v in env(default).items() if k.startswith("CKS_")}
    assert shared.items() <= env(cuda).items()


def test_the_gpu_extra_installs_onnxruntime_gpu() -> None:
    extras = tomllib.loads((PACKAGE_ROOT / "pyproject.toml").read_text())["project"]["optional-dependencies"]
    assert any(requirement.startswith("onnxruntime-gpu") for requirement in extras["gpu"])
