"""Imports point down the layers, and no two packages import each other.

The layers, top to bottom (docs/development.md shows the same list):

    service.serving, service.cli, service.deploy_ray      the roof: composes the service
    service.api                                            HTTP: parses and presents
    service.prediction, .calibration, .monitoring,         the use cases
      .pose, .evaluation, .feedback
    service.detector, service.conformal                    the model and the math
    service.infra, service.errors, service                 the ground floor

A module may import its own layer or one below. ``calibration_store`` and the client
(``keypoint_client``) import nothing of ``service``. Every import counts, also those inside
functions and under ``TYPE_CHECKING``.
"""

from __future__ import annotations

import ast
import itertools
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]
LAYERS: tuple[tuple[str, ...], ...] = (
    ("service.serving", "service.cli", "service.deploy_ray"),
    ("service.api",),
    (
        "service.prediction",
        "service.calibration",
        "service.monitoring",
        "service.pose",
        "service.evaluation",
        "service.feedback",
    ),
    ("service.detector", "service.conformal"),
    ("service.infra", "service.errors", "service"),
)


def module_name(path: Path) -> str:
    parts = path.relative_to(ROOT).with_suffix("").parts
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def imported_modules(path: Path) -> set[str]:
    """Every absolute module name a file imports (relative imports resolved)."""
    tree = ast.parse(path.read_text(encoding="utf-8"))
    package = module_name(path) if path.name == "__init__.py" else module_name(path).rpartition(".")[0]
    names: set[str] = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            names.update(alias.name for alias in node.names)
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:
                anchor = package.split(".")
                anchor = anchor[: len(anchor) - node.level + 1]
                base = ".".join([*anchor, base] if base else anchor)
            names.add(base)
            names.update(f"{base}.{alias.name}" for alias in node.names)
    return names


def owner(name: str, roots: tuple[str, ...]) -> str | None:
    """The longest of ``roots`` that ``name`` is, or lies in."""
    hits = [root for root in roots if name == root or name.startswith(root + ".")]
    return max(hits, key=len, default=None)


ALL_ROOTS = tuple(itertools.chain.from_iterable(LAYERS))
LAYER_OF = {root: depth for depth, roots in enumerate(LAYERS) for root in roots}


def service_files() -> list[Path]:
    return sorted((ROOT / "service").rglob("*.py"))


def edges() -> list[tuple[str, str, Path]]:
    """(importing package, imported package, file) for every import inside ``service``."""
    found = []
    for path in service_files():
        source = owner(module_name(path), ALL_ROOTS)
        for name in imported_modules(path):
            target = owner(name, ALL_ROOTS)
            if target is not None and source is not None and target != source:
                found.append((source, target, path))
    return found


def test_every_service_module_has_a_layer() -> None:
    homeless = [module_name(p) for p in service_files() if owner(module_name(p), ALL_ROOTS) == "service"]
    assert homeless == ["service"], "give each top-level module of service/ a layer in LAYERS"


def test_no_import_points_up() -> None:
    upward = sorted(
        {
            f"{path.relative_to(ROOT)}: {source} imports {target}"
            for source, target, path in edges()
            if LAYER_OF[target] < LAYER_OF[source]
        }
    )
    assert not upward, "\n".join(upward)


def test_no_two_packages_import_each_other() -> None:
    pairs = {(source, target) for source, target, _ in edges() if target != "service"}
    mutual = sorted(f"{a} <-> {b}" for a, b in pairs if (b, a) in pairs and a < b)
    assert not mutual, "\n".join(mutual)


@pytest.mark.parametrize("folder", ["calibration_store", "client"])
def test_the_store_and_the_client_import_nothing_of_service(folder: str) -> None:
    leaks = sorted(
        f"{path.relative_to(ROOT)}: {name}"
        for path in (ROOT / folder).rglob("*.py")
        for name in imported_modules(path)
        if owner(name, ("service",))
    )
    assert not leaks, "\n".join(leaks)


def test_the_http_plumbing_imports_only_the_ground_floor() -> None:
    """service.api.http (bodies, admission, problems, middlewares) serves every route: it is given
    what a use case knows, and imports none of them (nor the model and the math)."""
    allowed = ("service.api.http", "service.infra", "service.errors")
    leaks = sorted(
        f"{path.relative_to(ROOT)}: {name}"
        for path in (ROOT / "service" / "api" / "http").rglob("*.py")
        for name in imported_modules(path)
        if owner(name, ("service",)) and not owner(name, allowed)
    )
    assert not leaks, "\n".join(leaks)
