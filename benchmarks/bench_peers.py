"""The service (and its int8 variant) against the frameworks a user would serve the model with instead.

    python -m benchmarks.bench_peers             # ~14 min: 2 rounds, 8 s a point; docs/performance.md
    python -m benchmarks.bench_peers --quick     # ~1 min smoke run: 1 round, 1 s per point
    python -m benchmarks.bench_peers --peers FastAPI,LitServe --duration 5
    python -m benchmarks.bench_peers --gpu       # the model on a GPU (onnxruntime-gpu); own section

Needs wrk (``apt-get install -y wrk``) and the ``peers`` extra (``pip install -e '.[peers]'``:
LitServe, BentoML, Ray Serve). Every peer computes the service's sets with the service's own
functions (float32, as its users run it); each peer's answer is checked against the service's before
it is timed. The service also runs its bundled int8 variant (``CKS_MODEL_DIR``), a different model
checked against its own first answer. Writes the ``bench_peers`` section of docs/performance.md;
with ``--gpu`` every server runs the model through onnxruntime's CUDA provider (the service with
the ``cuda`` image's settings; no int8 variant) and the run writes the ``bench_peers_gpu`` section instead.
"""

from __future__ import annotations

import argparse
import os
import sys
import tempfile
import time
from pathlib import Path

import onnxruntime

from benchmarks.harness import (
    BOXES,
    PERFORMANCE_PAGE,
    Requests,
    load_sample,
    log,
    require_wrk,
    run_wrk,
    this_machine,
    write_section,
)
from benchmarks.peers.accelerator import CUDA, GPU_SETTINGS, on_gpu
from benchmarks.peers.measure import Plan, measure
from benchmarks.peers.profile import Profile, profile_under_load
from benchmarks.peers.report import PeerResults, goals, render
from benchmarks.peers.servers import PEERS, SERVICE, SERVICE_INT8, SERVICE_ON_GPU, Contender
from benchmarks.stages import in_process_limits
from service.infra.settings import DEFAULT_MODEL_DIR

PROFILE_CONCURRENCY = 16


def parse_args(argv: list[str] | None) -> argparse.Namespace:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="smoke run: 1 round, 1 s per point")
    parser.add_argument("--duration", type=float, help="seconds per point (default 8, quick 1)")
    parser.add_argument("--rounds", type=int, help="rounds over every server (default 2, quick 1)")
    parser.add_argument(
        "--peers", default=",".join(p.name for p in PEERS), help="comma-separated peers (default: all)"
    )
    parser.add_argument(
        "--output", type=Path, default=PERFORMANCE_PAGE, help="the page to write its section in"
    )
    parser.add_argument("--no-write", action="store_true", help="print the section, do not write the page")
    parser.add_argument("--no-profile", action="store_true", help="skip the py-spy profile of the service")
    parser.add_argument(
        "--gpu", action="store_true", help="every server runs the model on the GPU (onnxruntime-gpu's CUDA)"
    )
    args = parser.parse_args(argv)
    known = {p.name.lower(): p for p in PEERS}
    wanted = [name.strip().lower() for name in args.peers.split(",") if name.strip()]
    unknown = [name for name in wanted if name not in known]
    if unknown:
        parser.error(f"unknown peer(s) {unknown}; known: {', '.join(p.name for p in PEERS)}")
    services = [SERVICE_ON_GPU] if args.gpu else [SERVICE, SERVICE_INT8]  # int8 is a CPU variant
    args.contenders = [*services, *(known[name] for name in wanted)]
    args.section = "bench_peers_gpu" if args.gpu else "bench_peers"
    return args


def command_line(args: argparse.Namespace) -> str:
    parts = ["python -m benchmarks.bench_peers"]
    parts += ["--gpu"] if args.gpu else []
    parts += ["--quick"] if args.quick else []
    parts += [f"--duration {args.duration:g}"] if args.duration else []
    parts += [f"--rounds {args.rounds}"] if args.rounds else []
    peers = [c.name for c in args.contenders if c.is_peer]
    if len(peers) != len(PEERS):
        parts.append("--peers " + ",".join(peers))
    return " ".join(parts)


def run(args: argparse.Namespace) -> PeerResults:
    started = time.monotonic()
    machine = this_machine()
    log(f"machine: {machine.describe()}")
    plan = Plan.for_mode(args.quick, args.duration, args.rounds)
    sample = load_sample()
    with tempfile.TemporaryDirectory(prefix="cks-peers-") as directory:
        requests = Requests.write(Path(directory), sample)
        log(f"server logs in {directory} while the run lasts")
        runs = measure(args.contenders, requests, plan, Path(directory), log)
        service = args.contenders[0]
        profile = None if args.no_profile else profile_service(service, requests, plan, Path(directory))
    limits = in_process_limits(DEFAULT_MODEL_DIR, sample, BOXES, 20 if args.quick else 200)
    for limit in limits:
        log(
            f"in-process, {limit.boxes} box(es): {limit.core_ms:.2f} core-ms/request, limit "
            f"{limit.requests_per_s:.0f} req/s, best latency {limit.best_latency_ms:.2f} ms"
        )
    return PeerResults(
        command=command_line(args),
        machine=machine,
        load_at_end=os.getloadavg(),
        seconds=plan.seconds,
        rounds=plan.rounds,
        contenders=args.contenders,
        runs=runs,
        limits=limits,
        profile=profile,
        minutes=(time.monotonic() - started) / 60,
    )


def profile_service(service: Contender, requests: Requests, plan: Plan, directory: Path) -> Profile:
    """py-spy on the service at concurrency 16 with one box (its own server start, after the rounds)."""
    with service.running(directory / "service-profiled.log") as server:
        run_wrk(server.url, requests.scripts[1], 4, plan.warmup_seconds)
        profile = profile_under_load(server, requests.scripts[1], PROFILE_CONCURRENCY, plan.seconds)
    log(profile.problem or "profile: " + ", ".join(f"{k} {v:.0%}" for k, v in profile.shares.items()))
    return profile


def use_gpu() -> None:
    """Every server started from here runs the model on the GPU (unless ``CKS_*`` say otherwise)."""
    available = onnxruntime.get_available_providers()
    if CUDA not in available:
        sys.exit(f"--gpu needs onnxruntime-gpu's {CUDA}; this onnxruntime has {', '.join(available)}")
    for name, value in GPU_SETTINGS.items():
        os.environ.setdefault(name, value)
    if not on_gpu():
        sys.exit(f"--gpu, but CKS_EXECUTION_PROVIDERS={os.environ['CKS_EXECUTION_PROVIDERS']} has no CUDA")


def main(argv: list[str] | None = None) -> int:
    args = parse_args(argv)
    require_wrk()
    if args.gpu:
        use_gpu()
    results = run(args)
    text = render(results)
    log("\n" + text)
    if not args.no_write:
        write_section(args.output, args.section, text)
        log(f"wrote the {args.section} section of {args.output}")
    missed = [goal.text for goal in goals(results) if not goal.met]
    log(f"goals: {len(goals(results)) - len(missed)} met, {len(missed)} NOT met")
    return 0


if __name__ == "__main__":
    sys.exit(main())
