"""``keypoint-service serve`` with proposed code changes applied at start-up, to measure them.

The benchmark cannot edit ``service/``; instead this replaces module functions before the
server starts (``CKS_BENCH_PATCHES``, comma-separated):

- ``no-spinning``: the onnxruntime session gets ``session.intra_op.allow_spinning = 0``
  (``service.detector.runtime._create_session``).

Only valid with ``CKS_WORKERS=1`` (worker processes would import the unpatched modules).

    CKS_BENCH_PATCHES=no-spinning python -m benchmarks.service_bench.patched_serve
"""

from __future__ import annotations

import os
import sys
from pathlib import Path

import onnxruntime as ort

from benchmarks.service_bench.raw import make_session
from service import cli
from service.detector import runtime

PATCHES_VARIABLE = "CKS_BENCH_PATCHES"


def _session_without_spinning(model_path: Path, intra_op_threads: int) -> ort.InferenceSession:
    return make_session(Path(model_path).parent, intra_op_threads, spinning=False)


def apply(patches: list[str]) -> None:
    for patch in patches:
        if patch == "no-spinning":
            runtime._create_session = _session_without_spinning
        elif patch:
            raise SystemExit(f"unknown patch {patch!r} in {PATCHES_VARIABLE}")


def main() -> int:
    apply(os.environ.get(PATCHES_VARIABLE, "").split(","))
    return cli.main(["serve"])


if __name__ == "__main__":
    sys.exit(main())
