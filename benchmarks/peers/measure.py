"""Running the load: every contender, every point, rounds in alternating order; medians."""

from __future__ import annotations

import statistics
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

from benchmarks.harness import BOXES, LoadResult, Requests, run_wrk
from benchmarks.peers.accelerator import on_gpu
from benchmarks.peers.answers import GPU_TOLERANCE, TOLERANCE, difference, post
from benchmarks.peers.servers import Contender

CONCURRENCIES = (1, 4, 16)
Point = tuple[int, int]  # (boxes per image, concurrency)


@dataclass(frozen=True)
class Plan:
    seconds: float
    warmup_seconds: float
    rounds: int

    @staticmethod
    def for_mode(quick: bool, seconds: float | None, rounds: int | None) -> Plan:
        plan = Plan(1.0, 1.0, 1) if quick else Plan(8.0, 2.0, 2)
        return Plan(seconds or plan.seconds, plan.warmup_seconds, rounds or plan.rounds)


@dataclass
class Runs:
    """Every wrk result per contender and point, in the order measured."""

    results: dict[str, dict[Point, list[LoadResult]]] = field(default_factory=dict)
    core_ms: dict[str, dict[Point, list[float]]] = field(default_factory=dict)  # server CPU per request

    def add(self, name: str, point: Point, result: LoadResult, cpu_seconds: float) -> None:
        self.results.setdefault(name, {}).setdefault(point, []).append(result)
        per_request = cpu_seconds * 1e3 / max(result.requests, 1)
        self.core_ms.setdefault(name, {}).setdefault(point, []).append(per_request)

    def cpu(self, name: str, point: Point) -> float:
        return statistics.median(self.core_ms[name][point])

    def rate(self, name: str, point: Point) -> float:
        return statistics.median(r.requests_per_s for r in self.results[name][point])

    def p50(self, name: str, point: Point) -> float:
        return statistics.median(r.p50_ms for r in self.results[name][point])

    def errors(self, name: str) -> int:
        return sum(r.errors for runs in self.results[name].values() for r in runs)


def check_answers(
    url: str, requests: Requests, reference: dict[int, dict], variant: str | None = None
) -> dict[int, dict]:
    """The contender's answers; ``AnswerMismatch`` unless they equal ``reference`` (when given), name
    ``variant`` as their ``model.variant`` (when given) and give every box its keypoints."""
    answers = {boxes: post(url, *requests.bodies[boxes]) for boxes in BOXES}
    for boxes, answer in answers.items():
        if variant is not None and answer["model"]["variant"] != variant:
            raise AnswerMismatch(f"{boxes} box(es): model {answer['model']['variant']}, not {variant}")
        if (found := sum(1 for i in answer["instances"] if i["keypoints"])) != boxes:
            raise AnswerMismatch(f"{boxes} box(es): {found} instance(s) with keypoints")
    for boxes, expected in reference.items():
        if problem := difference(expected, answers[boxes], GPU_TOLERANCE if on_gpu() else TOLERANCE):
            raise AnswerMismatch(f"{boxes} box(es): {problem}")
    return answers


class AnswerMismatch(Exception):
    """A peer's sets differ from the service's (or a variant's from its own first answer): timing it
    would compare different work."""


def measure(
    contenders: list[Contender], requests: Requests, plan: Plan, logs: Path, log: Callable[[str], None]
) -> Runs:
    """Each round starts every contender in turn (the order reversed every other round) and checks its
    answers: a peer's against the service's (the first contender, so measured first), a service
    variant's against its own first answer (another model gives other sets); then runs every point."""
    runs, references = Runs(), {}
    for round_number in range(plan.rounds):
        order = contenders if round_number % 2 == 0 else contenders[::-1]
        for contender in order:
            with contender.running(logs / f"{contender.name.replace(' ', '-')}.log") as server:
                key = contenders[0].name if contender.is_peer else contender.name
                answers = check_answers(server.url, requests, references.get(key, {}), contender.variant)
                references.setdefault(key, answers)
                for boxes in BOXES:
                    run_wrk(server.url, requests.scripts[boxes], 4, plan.warmup_seconds)
                for boxes in BOXES:
                    for concurrency in CONCURRENCIES:
                        cpu_before = server.cpu_seconds()
                        result = run_wrk(server.url, requests.scripts[boxes], concurrency, plan.seconds)
                        cpu = server.cpu_seconds() - cpu_before
                        runs.add(contender.name, (boxes, concurrency), result, cpu)
                        log(format_result(round_number, contender.name, boxes, result, cpu))
    return runs


def format_result(round_number: int, name: str, boxes: int, result: LoadResult, cpu_seconds: float) -> str:
    return (
        f"round {round_number + 1} {name:<12} {boxes} box(es) c={result.concurrency:<2} "
        f"{result.requests_per_s:7.1f} req/s  p50 {result.p50_ms:6.1f} ms  p99 {result.p99_ms:6.1f} ms  "
        f"{cpu_seconds * 1e3 / max(result.requests, 1):5.2f} server core-ms/request  errors {result.errors}"
    )
