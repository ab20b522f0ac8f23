"""The certified outer bound (docs/pose.md, "Outer"): a convex relaxation of PURSE solved with Clarabel.

Each keypoint's constraint is a second-order cone in (R, t) (Yang & Pavone, CVPR 2023, eq. 8); SO(3)
is replaced by its convex hull through the quaternion lift R = A(Q), Q PSD, tr Q = 1 (Saunderson,
Parrilo & Willsky 2015), plus depth cuts. Seven conic programs bound the translation offsets along
the ray frame of t_hat and the rotation angle, each bound recomputed here from the dual (weak duality):
``certified`` only when every certificate checks out and the bounds dominate the poses found. The
whole-space relaxation is loose, so a best-first search (``_Search``) tightens it over rotation wedges
(cells.Wedge); the bounds, the worst over the wedges left, are valid at every step.
"""

from __future__ import annotations

import importlib.util
import itertools
import math
from dataclasses import dataclass, replace
from functools import cache

import numpy as np

from .camera import ray_frame
from .cells import SIDES, Wedge
from .estimate import whitening
from .membership import Pose
from .rotations import QUATERNION_BASIS, left_product, rotation_angle_deg, to_quaternion

_TRIANGLE = [(a, b) for b in range(4) for a in range(b + 1)]  # Clarabel's svec order: upper, by column
_Q = len(_TRIANGLE)  # 10 entries of the 4x4 quaternion moment matrix
_N = _Q + 3  # + the scaled translation offset
_AGREEMENT = 1e-6  # relative primal-dual agreement required of a certificate
_UPPER = tuple(np.array(index) for index in zip(*_TRIANGLE, strict=True))  # Q's entries in svec order
_LOWER = _UPPER[::-1]
_DIAGONAL = _UPPER[0] == _UPPER[1]
_SVEC_SCALE = np.where(_DIAGONAL, 1.0, math.sqrt(2.0))
# (16, _Q): u^T Q w = (u w^T).ravel() @ this over Q's upper triangle (unscaled entries)
_OUTER_TO_TRIANGLE = np.zeros((4, 4, _Q))
_OUTER_TO_TRIANGLE[(*_UPPER, np.arange(_Q))] = _OUTER_TO_TRIANGLE[(*_LOWER, np.arange(_Q))] = 1.0
_OUTER_TO_TRIANGLE = _OUTER_TO_TRIANGLE.reshape(16, _Q)
_ROTATION_MAP = QUATERNION_BASIS.reshape(9, 16) @ _OUTER_TO_TRIANGLE  # row-major vec(R) from Q


def _minor_rows() -> np.ndarray:
    """(18, _N): -A rows of Q's six 2x2 principal minors as SOC(3) cones (Q_aa + Q_bb, 2 Q_ab,
    Q_aa - Q_bb), each a cone exactly when [[Q_aa, Q_ab], [Q_ab, Q_bb]] is PSD."""
    column = {entry: k for k, entry in enumerate(_TRIANGLE)}
    rows = np.zeros((6, 3, _N))
    for k, (a, b) in enumerate(entry for entry in _TRIANGLE if entry[0] != entry[1]):
        rows[k, 0, [column[a, a], column[b, b]]] = -1.0
        rows[k, 1, column[a, b]] = -2.0
        rows[k, 2, [column[a, a], column[b, b]]] = -1.0, 1.0
    return rows.reshape(18, _N)


_MINOR_ROWS = _minor_rows()


def relaxation_available() -> bool:
    """Whether the `pose` extra (Clarabel) is installed."""
    return importlib.util.find_spec("clarabel") is not None


@cache
def _clarabel():
    import clarabel  # the `pose` extra; imported on first use, not at service start

    return clarabel


@dataclass(frozen=True)
class OuterBound:
    """Upper bounds on the pose error over PURSE from the relaxation (None: not available)."""

    certified: bool
    status: str
    rotation_deg: float | None = None
    translation: float | None = None
    empty: bool = False  # the relaxation, hence PURSE, has no point


@dataclass(frozen=True)
class _Program:
    """A x + s = b, s in (zero(1), PSD triangle(4) or, with ``minors``, SOC(3) per 2x2 principal minor
    of Q, SOC(3) per keypoint, nonnegative(cuts)); x = (Q's upper triangle, (t - t_hat) / scale)."""

    matrix: np.ndarray
    offset: np.ndarray
    keypoints: int
    cuts: int
    scale: float
    reach: float  # every pose in PURSE has || t - t_hat || / scale <= reach (inf: no such bound)
    minors: bool = False


def _program(estimate: Pose, camera: np.ndarray, keypoints_3d, centers, shapes) -> _Program:
    """The whole-space relaxation."""
    scale = float(np.linalg.norm(estimate.translation)) or 1.0
    trace = np.zeros(_N)
    trace[:_Q] = _DIAGONAL
    rows = [trace[None], np.hstack([-np.diag(_SVEC_SCALE), np.zeros((_Q, 3))])]
    offsets = [np.ones(1), np.zeros(_Q)]
    # p_i / scale = linear_i x + t_hat / scale, with R X_i linear in Q
    linears = [
        np.hstack([np.kron(np.eye(3), point[None]) @ _ROTATION_MAP, np.eye(3)])
        for point in keypoints_3d / scale
    ]
    origin = estimate.translation / scale
    for linear, center, w in zip(linears, centers, whitening(shapes), strict=True):
        cone = np.vstack([[0.0, 0.0, 1.0], w @ (camera[:2] - np.outer(center, camera[2]))])
        cone /= np.abs(cone).max()  # a positive scale keeps the cone and evens the rows' magnitudes
        rows.append(-cone @ linear)
        offsets.append(cone @ origin)
    cuts, distance_bound = _rigidity(camera, keypoints_3d, centers, shapes, scale)
    for i, j, slope_i, slope_j, distance in cuts:  # slope_i z_i + slope_j z_j >= d_ij
        rows.append(-(slope_i * linears[i][2] + slope_j * linears[j][2])[None])
        offsets.append(np.array([(slope_i + slope_j) * origin[2] - distance]))
    reach = (distance_bound + scale) / scale
    return _Program(np.vstack(rows), np.concatenate(offsets), len(centers), len(cuts), scale, reach)


def _with_minors(program: _Program) -> _Program:
    """``program`` with Q's PSD cone replaced by its six 2x2 principal minors: weaker, but as tight
    within a wedge's sides in the median, at about half of Clarabel's solve."""
    matrix, offset = program.matrix, program.offset
    return replace(
        program,
        matrix=np.vstack([matrix[:1], _MINOR_ROWS, matrix[1 + _Q :]]),
        offset=np.concatenate([offset[:1], np.zeros(len(_MINOR_ROWS)), offset[1 + _Q :]]),
        minors=True,
    )


def _with_cuts(program: _Program, rows: np.ndarray, offsets) -> _Program:
    """``program`` with the linear cuts rows x <= offsets."""
    matrix, offset = np.vstack([program.matrix, rows]), np.append(program.offset, offsets)
    return replace(program, matrix=matrix, offset=offset, cuts=program.cuts + len(rows))


def _bilinear_rows(u: np.ndarray, w: np.ndarray) -> np.ndarray:
    """u_k^T Q w_k for every row k of u and w (k, 4), as rows over Q's upper triangle (unscaled)."""
    return (u[:, :, None] * w[:, None, :]).reshape(len(u), 16) @ _OUTER_TO_TRIANGLE


def _rigidity(camera: np.ndarray, keypoints_3d: np.ndarray, centers, shapes, scale: float):
    """Depth cuts (i, j, s_i, s_j, d_ij / scale): s_i z_i + s_j z_j >= d_ij, as ||p_i|| <= s_i z_i over
    set i, keep the relaxation (which holds R = 0, t = 0) off the camera; a chain through the bounded
    sets (all pairs cost a fifth of each solve and tighten nothing). And an upper bound on ||t|| over
    PURSE (inf when no two sets are apart): the rays through disjoint sets make an angle with sine at
    least gap_ij / (s_i s_j), so ||p_i|| <= d_ij s_i s_j / gap_ij and ||t|| <= ||p_i|| + ||X_i||."""
    values = np.linalg.eigvalsh(shapes)
    bounded, inverse = values[:, 0] > 0, np.linalg.inv(camera)
    rays = np.c_[centers, np.ones(len(centers))] @ inverse.T
    radius = np.where(bounded, 1.0 / np.sqrt(np.where(bounded, values[:, 0], 1.0)), np.inf)
    radius = radius * max(inverse[0, 0], inverse[1, 1])  # semi-major axis / f
    slopes, kept = np.linalg.norm(rays, axis=1) + radius, np.flatnonzero(bounded)
    scaled = keypoints_3d / scale
    cuts = [
        (i, j, slopes[i], slopes[j], float(np.linalg.norm(scaled[i] - scaled[j])))
        for i, j in zip(kept[:-1], kept[1:], strict=True)
    ]
    best = math.inf
    for i, j in itertools.permutations(kept, 2):
        gap = float(np.linalg.norm(rays[i, :2] - rays[j, :2]) - radius[i] - radius[j])
        if gap > 0:
            distance = float(np.linalg.norm(keypoints_3d[i] - keypoints_3d[j]))
            best = min(best, distance * slopes[i] * slopes[j] / gap + float(np.linalg.norm(keypoints_3d[i])))
    return cuts, best


@cache
def _cones(keypoints: int, cuts: int, minors: bool = False) -> tuple:
    clarabel = _clarabel()
    cones = [clarabel.ZeroConeT(1)]
    cones += [clarabel.SecondOrderConeT(3) for _ in range(6)] if minors else [clarabel.PSDTriangleConeT(4)]
    cones += [clarabel.SecondOrderConeT(3) for _ in range(keypoints)]
    return tuple(cones + ([clarabel.NonnegativeConeT(cuts)] if cuts else []))


def _project_dual(dual: np.ndarray, program: _Program) -> np.ndarray:
    """The multipliers projected onto the dual cones (all self-dual; the zero cone's dual is free)."""
    projected, start, keypoints, cuts = dual.copy(), 1, program.keypoints, program.cuts
    if program.minors:
        keypoints += 6
    else:
        matrix = np.zeros((4, 4))
        matrix[_UPPER] = matrix[_LOWER] = projected[1 : 1 + _Q] / _SVEC_SCALE
        values, vectors = np.linalg.eigh(matrix)
        projected[1 : 1 + _Q] = ((vectors * np.maximum(values, 0.0)) @ vectors.T)[_UPPER] * _SVEC_SCALE
        start = 1 + _Q
    cones = projected[start : start + 3 * keypoints].reshape(keypoints, 3)  # a view: edits land
    heads, norms = cones[:, 0].copy(), np.sqrt(np.einsum("ij,ij->i", cones[:, 1:], cones[:, 1:]))
    outside = norms > heads  # Euclidean projection onto the second-order cone where outside it
    if outside.any():
        levels = np.where(norms <= -heads, 0.0, (heads + norms) / 2)
        scale = np.divide(levels, norms, out=np.zeros_like(norms), where=norms > 0)
        cones[outside, 0] = levels[outside]
        cones[outside, 1:] *= scale[outside, None]
    if cuts:
        projected[-cuts:] = np.maximum(projected[-cuts:], 0.0)
    return projected


@dataclass(frozen=True)
class _Solved:
    status: str
    bound: float  # our weak-duality lower bound on min q^T x over PURSE
    agrees: bool  # the certificate checks out (of optimality, or of infeasibility)


_RETRIES = ({"equilibrate_enable": False}, {"max_step_fraction": 0.95})  # when a solve stalls


def _solver(program: _Program, objective: np.ndarray, pattern=None, **options):
    """A Clarabel solver of ``program``; ``pattern`` (data, rows, columns in column-major order)
    keeps entries that are zero here but not in the programs that will update it."""
    from scipy import sparse  # clarabel's own dependency

    clarabel = _clarabel()
    settings = clarabel.DefaultSettings()
    settings.verbose = False
    settings.iterative_refinement_enable = False  # a fifth of each solve; the certificate is checked here
    for name, value in options.items():
        setattr(settings, name, value)
    if pattern is None:
        rows, columns = np.nonzero(program.matrix.T)
        pattern = program.matrix.T[rows, columns], rows, columns
    data, rows, columns = pattern  # built directly: scipy's conversion of a dense array costs a solve
    pointers = np.searchsorted(rows, np.arange(_N + 1))
    matrix = sparse.csc_matrix((data, columns, pointers), shape=program.matrix.shape)
    cones = list(_cones(program.keypoints, program.cuts, program.minors))
    return clarabel.DefaultSolver(
        sparse.csc_matrix((_N, _N)), objective, matrix, program.offset, cones, settings
    )


def _status(solution) -> str:
    return str(solution.status).split(".")[-1]


def _outcome(program: _Program, objective: np.ndarray, solution) -> _Solved:
    """What a solution proves, its certificate checked here (a stalled solve is retried).

    With z the multipliers projected onto the dual cones and r = q + A^T z, every feasible x has
    q^T x = -b^T z + z^T s + r^T x >= -b^T z - |r_Q|_1 - ||r_t|| reach (z^T s >= 0, |Q_ab| <= 1). An
    infeasibility certificate (q = 0) proves the relaxation empty when b^T z < 0 and that bound is > 0.
    """
    for options in _RETRIES:
        if _status(solution) in ("Solved", "PrimalInfeasible"):
            break
        # Clarabel sometimes stalls these programs at "AlmostSolved"; other settings solve them
        solution = _solver(program, objective, **options).solve()
    status = _status(solution)
    if status not in ("Solved", "PrimalInfeasible"):
        return _Solved(status, math.nan, False)
    z = _project_dual(np.asarray(solution.z), program)
    residual = (objective if status == "Solved" else 0.0) + program.matrix.T @ z
    gap = float(program.offset @ z)
    lower = -gap - float(np.abs(residual[:_Q]).sum())
    bound = lower - float(np.linalg.norm(residual[_Q:])) * program.reach
    if status == "PrimalInfeasible":
        return _Solved(status, bound, gap < 0 and bound > 0)
    primal = float(objective @ np.asarray(solution.x))
    return _Solved(status, bound, abs(primal - lower) <= _AGREEMENT * (1.0 + abs(primal)))


def _empty(verified: bool) -> OuterBound:
    if verified:
        return OuterBound(True, "relaxation infeasible: no pose is consistent with the sets", empty=True)
    return OuterBound(False, "relaxation reported infeasible, certificate not verified")


def _angle(trace: float) -> float:
    """The rotation angle (radians) of a rotation with this trace of R_hat^T R."""
    return math.acos(min(1.0, max(-1.0, (trace - 1.0) / 2.0)))


@dataclass(frozen=True)
class _RootBound:
    """What the whole-space relaxation proves (all in the program's scaled units)."""

    status: str  # "bounded", "empty" (infeasibility verified) or why it failed
    extents: np.ndarray | None = None  # (6,) upper bounds on +-e_k^T (t - t_hat) / scale
    smallest_trace: float = math.nan  # lower bound on tr(R_hat^T R)
    verified: bool = False


def _objectives(estimate: Pose, frame: np.ndarray) -> list[np.ndarray]:
    """The seven objectives: min -(+-e_k)^T dt for the ray frame's axes, then min tr(R_hat^T R)."""
    translation = [np.concatenate([np.zeros(_Q), -sign * axis]) for axis in frame for sign in (1.0, -1.0)]
    return [*translation, np.concatenate([estimate.rotation.reshape(9) @ _ROTATION_MAP, np.zeros(3)])]


def _proven(objective: int, solved: _Solved) -> float:
    """The certified bound of a solved program: an extent (scaled) or a rotation angle (radians)."""
    return -solved.bound if objective < 6 else _angle(solved.bound)


def _bound_root(program: _Program, objectives: list[np.ndarray]) -> _RootBound:
    """The seven bounds over the whole rotation space."""
    values, verified = [], True
    for k, objective in enumerate(objectives):
        if k == 0:
            solver = _solver(program, objective)
        else:
            solver.update(q=objective)
        solved = _outcome(program, objective, solver.solve())
        if solved.status == "PrimalInfeasible":
            status = "empty" if solved.agrees else "infeasibility certificate not verified"
            return _RootBound(status, verified=solved.agrees)
        if solved.status != "Solved":
            return _RootBound(f"{'translation' if k < 6 else 'rotation'} program: {solved.status}")
        values.append(_proven(k, solved))
        verified = verified and solved.agrees
    return _RootBound("bounded", np.array(values[:6]), 1.0 + 2.0 * math.cos(values[6]), verified)


def outer_bound(
    estimate: Pose,
    camera: np.ndarray,
    keypoints_3d: np.ndarray,
    centers: np.ndarray,
    shapes: np.ndarray,
    sampled: list[Pose] | None = None,
    programs: int = 0,
) -> OuterBound:
    """Certified upper bounds on the rotation and translation error over PURSE (see the module doc):
    the whole space's, tightened by ``programs`` conic programs of the search over rotation wedges
    around the estimate."""
    if not relaxation_available():
        return OuterBound(False, "the pose extra (clarabel) is not installed")
    with np.errstate(all="ignore"):
        program = _program(estimate, camera, keypoints_3d, centers, shapes)
    if not (np.isfinite(program.matrix).all() and np.isfinite(program.offset).all()):
        return OuterBound(False, "relaxation not posed: the data overflow (extreme camera matrix or sets)")
    if not math.isfinite(program.reach):
        return OuterBound(
            False, "no proven bound on ||t|| over PURSE (no two sets apart): nothing to certify with"
        )
    objectives = _objectives(estimate, ray_frame(estimate.translation))
    root = _bound_root(program, objectives)
    if root.status != "bounded":
        return _empty(root.verified) if root.status == "empty" else OuterBound(False, root.status)
    found = sampled or []
    shifts = [float(np.linalg.norm(p.translation - estimate.translation)) for p in found]
    distances = list(
        zip(shifts, [rotation_angle_deg(estimate.rotation, p.rotation) for p in found], strict=True)
    )
    bounds = np.append(root.extents, _angle(root.smallest_trace))
    if programs <= 0:
        return _finish(program.scale, bounds, root.verified, distances, "whole rotation space")
    search = _Search(_WedgePrograms(program, estimate.rotation, objectives), distances)
    leaves = search.run(bounds, programs)
    if not leaves:
        return OuterBound(False, "every rotation cell proven empty, yet the estimate is in PURSE")
    bounds = np.max([leaf.bounds for leaf in leaves], axis=0)
    detail = f"{search.spent} programs, {len(leaves)} rotation cells"
    return _finish(program.scale, bounds, root.verified, distances, detail)


def _finish(scale, bounds, verified, distances, detail) -> OuterBound:
    rotation, translation, slack = math.degrees(bounds[6]), _radius(bounds, scale), 1e-6
    certified = verified and all(
        angle <= rotation + slack and shift <= translation * (1 + slack) + slack for shift, angle in distances
    )
    status = "solved, certificate verified" if certified else "solved, certificate not verified"
    return OuterBound(certified, f"{status} ({detail})", rotation, translation)


def _radius(bounds: np.ndarray, scale: float) -> float:
    """The translation radius from the six extents (a box around the estimate)."""
    extents = bounds[:6].clip(min=0.0)
    return scale * math.sqrt(sum(max(extents[2 * k], extents[2 * k + 1]) ** 2 for k in range(3)))


#: the search stops once the certified bounds are within these factors of the poses found in PURSE
#: (1.25 / 1.04 against 1.2 / 1.03: 7 % less CPU per instance for median outer/inner 1.22 against
#: 1.19 rotation, same certificates; docs/pose.md)
ROTATION_TOLERANCE = 1.25
TRANSLATION_TOLERANCE = 1.04


@dataclass
class _Leaf:
    """A rotation wedge with upper bounds on the six extents and the rotation angle over its poses;
    ``solved[k]``: bound k was proven for this wedge (otherwise it is an ancestor's, valid too)."""

    cell: Wedge
    bounds: np.ndarray
    solved: np.ndarray

    def children(self, radius: float) -> list[_Leaf]:
        leaves = [_Leaf(c, self.bounds.copy(), np.zeros(7, dtype=bool)) for c in self.cell.split(radius)]
        for leaf in leaves:  # no rotation of a wedge is farther than its far corner: a bound for free
            leaf.bounds[6] = min(leaf.bounds[6], leaf.cell.farthest_angle())
        return leaves


class _WedgePrograms:
    """The relaxations of one search's wedges: the whole-space program (Q's cone by its minors) plus
    a wedge's sides a_k^T Q b_k <= 0 (cells.SIDES), one Clarabel solver whose data is updated per
    wedge (the sides' rows kept dense, so the sparsity stays): half the cost of setting up each."""

    def __init__(self, program: _Program, estimate: np.ndarray, objectives: list[np.ndarray]) -> None:
        program = _with_minors(program)
        self.program, self.objectives = program, objectives
        self._anchor = left_product(to_quaternion(estimate))
        sides = len(SIDES[0])
        self._restricted = _with_cuts(program, np.zeros((sides, _N)), np.zeros(sides))  # sides rewritten
        pattern = np.vstack([program.matrix != 0, np.tile(np.arange(_N) < _Q, (sides, 1))])
        self._rows, self._columns = np.nonzero(pattern.T)  # column-major: compressed columns
        self._data = self._restricted.matrix.T[self._rows, self._columns]
        self._on_sides = self._columns >= len(program.matrix)  # by column of Q, then by side
        self._solver = None

    def solve(self, wedge: Wedge, quantity: int) -> _Solved:
        forms = wedge.forms(self._anchor)
        sides = _bilinear_rows(-forms[SIDES[0]], forms[SIDES[1]])
        restricted, data = self._restricted, self._data
        restricted.matrix[len(self.program.matrix) :, :_Q] = sides
        data[self._on_sides] = sides.T.ravel()
        objective = self.objectives[quantity]
        if self._solver is None:
            self._solver = _solver(restricted, objective, pattern=(data, self._rows, self._columns))
        else:
            self._solver.update(A=data, q=objective)
        return _outcome(restricted, objective, self._solver.solve())


class _Search:
    """Best-first branch-and-bound over rotation wedges around the estimate: each step proves one bound
    for the leaf attaining the loosest quantity, or splits that leaf once its bound is proven. It stops
    after ``budget`` programs, or once both bounds are within their tolerances of the poses reached."""

    def __init__(self, programs: _WedgePrograms, distances: list[tuple[float, float]]) -> None:
        self.programs, self.spent, self.reached = programs, 0, None
        if distances:  # the largest (translation, rotation in radians) distances to poses in PURSE
            self.reached = max(d[0] for d in distances), math.radians(max(d[1] for d in distances))

    def run(self, root_bounds: np.ndarray, budget: int) -> list[_Leaf]:
        """The leaves left (empty: every wedge was proven empty)."""
        radius = float(root_bounds[6])
        roots = Wedge.around(radius)  # one wedge is split at once, the four faces solved first
        leaves = [_Leaf(w, root_bounds.copy(), np.full(7, len(roots) == 1)) for w in roots]
        while leaves:
            table = np.array([leaf.bounds for leaf in leaves])
            bounds = table.max(axis=0)
            quantity = self._loosest(bounds)
            if quantity is None:
                break
            index = int(table[:, quantity].argmax())
            leaf = leaves[index]
            radius = min(radius, float(bounds[6]))  # PURSE's rotations are within this of R_hat
            if leaf.cell.nearest_angle() > radius:  # its own bound is at most radius: no pose of PURSE
                leaves.pop(index)
            elif leaf.solved[quantity]:  # each split unproves a bound: splits stay fewer than programs + 7
                leaves[index : index + 1] = leaf.children(radius)
            elif self.spent == budget:
                break
            elif not self._prove(leaf, quantity):
                leaves.pop(index)
        return leaves

    def _prove(self, leaf: _Leaf, quantity: int) -> bool:
        """Solve one program for ``leaf``; False when it proves the wedge empty."""
        self.spent += 1
        leaf.solved[quantity] = True
        solved = self.programs.solve(leaf.cell, quantity)
        if solved.status == "PrimalInfeasible" and solved.agrees:
            return False
        if solved.status == "Solved" and solved.agrees:
            value = _proven(quantity, solved)
            if quantity == 6:
                value = min(value, leaf.cell.farthest_angle())
            leaf.bounds[quantity] = min(leaf.bounds[quantity], value)
        return True

    def _loosest(self, bounds: np.ndarray) -> int | None:
        """The bound to tighten next: the largest extent or the rotation, whichever is further (relative
        to its tolerance) from the poses reached (alternately without any); None once both are within."""
        extent = int(np.argmax(bounds[:6]))
        reached = self.reached
        if reached is None or min(reached) <= 0:
            return extent if self.spent % 2 == 0 else 6
        gaps = (
            _radius(bounds, self.programs.program.scale) / reached[0] / TRANSLATION_TOLERANCE,
            bounds[6] / reached[1] / ROTATION_TOLERANCE,
        )
        if max(gaps) <= 1.0:
            return None
        return extent if gaps[0] >= gaps[1] else 6
