"""The certified outer bound: a convex relaxation of PURSE solved with Clarabel (optional extra).

Each keypoint's constraint is a second-order cone in (R, t) (Yang & Pavone, CVPR 2023, eq. 8):
with p_i = R X_i + t, z_i = p_i[2] and W_i^T W_i = L_i,
    || W_i (K[:2] - c_i e_3^T) p_i || <= z_i,
which is (y_i - c_i)^T L_i (y_i - c_i) <= 1 multiplied by z_i^2 > 0. PURSE is these cones
intersected with SO(3). Replacing SO(3) by its convex hull, written exactly through the unit
quaternion lift R = A(Q), Q = q q^T relaxed to {Q PSD, tr Q = 1} (Saunderson, Parrilo & Willsky,
SIAM J. Optim. 2015), plus valid depth cuts, gives a convex set containing PURSE. Over it (or
over each rotation cell of a branch-and-bound, cells.py) we solve small conic programs:
    max e_k^T (t - t_hat) for e_k in +-{ray frame of t_hat}  -> box, then radius, on the translation error
    min tr(R_hat^T R)                                         -> angle bound on the rotation error
Each bound is read from the dual: Clarabel's multipliers are projected onto the dual cones and
the weak-duality bound is recomputed here (the certificate check), its residual in the
translation bounded with a proven bound on ||t|| over PURSE (``_distance_bound``). ``certified``
is True only when every program is solved, the recomputed dual bound agrees with the primal
value, and it dominates the sampled poses. A relaxation whose infeasibility certificate checks
out the same way proves PURSE empty.

The whole-space relaxation is loose: conv SO(3) holds the shrunk rotations alpha R, and
(alpha R, alpha t) projects like (R, t), so the relaxation reaches towards the camera and far in
rotation. Restricting the rotations to a cell keeps alpha near 1, so the search (``_Search``) cuts
the rotations near the estimate into wedges (boxes of Gibbs vectors, cells.Wedge, whose sides are
linear constraints on the moment matrix, exact for the wedge's rotations), best-first where a
bound is attained, one conic program per step: the bounds are the worst over the cells left,
valid at every step.
"""

from __future__ import annotations

import importlib.util
import math
from dataclasses import dataclass, replace
from functools import cache

import numpy as np

from .camera import ray_frame
from .cells import SIDES, Wedge, root_cells
from .estimate import whitening
from .membership import Pose
from .rotations import QUATERNION_BASIS, left_product, rotation_angle_deg, to_quaternion

_TRIANGLE = [(a, b) for b in range(4) for a in range(b + 1)]  # Clarabel's svec order: upper, by column
_Q = len(_TRIANGLE)  # 10 entries of the 4x4 quaternion moment matrix
_N = _Q + 3  # + the scaled translation offset
_AGREEMENT = 1e-6  # relative primal-dual agreement required of a certificate


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


def _rotation_map() -> np.ndarray:
    """(9, 10): row-major vec(R) as a linear function of Q's upper triangle (unscaled entries)."""
    mapping = np.zeros((9, _Q))
    for column, (a, b) in enumerate(_TRIANGLE):
        block = QUATERNION_BASIS[:, :, a, b] + (QUATERNION_BASIS[:, :, b, a] if a != b else 0.0)
        mapping[:, column] = block.reshape(9)
    return mapping


_ROTATION_MAP = _rotation_map()
_SVEC_SCALE = np.array([1.0 if a == b else math.sqrt(2.0) for a, b in _TRIANGLE])
_UPPER = tuple(np.array(index) for index in zip(*_TRIANGLE, strict=True))  # Q's entries in svec order
_LOWER = _UPPER[::-1]


def _minor_rows() -> np.ndarray:
    """(18, _N): -A rows of the six 2x2 principal minors of Q as SOC(3) cones,
    (Q_aa + Q_bb, 2 Q_ab, Q_aa - Q_bb), each a cone exactly when [[Q_aa, Q_ab], [Q_ab, Q_bb]] is PSD."""
    column = {entry: k for k, entry in enumerate(_TRIANGLE)}
    rows = np.zeros((6, 3, _N))
    for k, (a, b) in enumerate(entry for entry in _TRIANGLE if entry[0] != entry[1]):
        rows[k, 0, [column[a, a], column[b, b]]] = -1.0
        rows[k, 1, column[a, b]] = -2.0
        rows[k, 2, [column[a, a], column[b, b]]] = -1.0, 1.0
    return rows.reshape(18, _N)


_MINOR_ROWS = _minor_rows()


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
    minors: bool = False  # Q's cone: its six 2x2 principal minors (SOC(3) each), not PSD(4)


def _program(estimate: Pose, camera: np.ndarray, keypoints_3d, centers, shapes) -> _Program:
    """The whole-space relaxation; ``_capped`` restricts it to a rotation cell."""
    scale = float(np.linalg.norm(estimate.translation)) or 1.0
    rows, offsets = [], []
    trace = np.zeros(_N)
    trace[[i for i, (a, b) in enumerate(_TRIANGLE) if a == b]] = 1.0
    rows.append(trace[None])
    offsets.append(np.ones(1))
    rows.append(np.hstack([-np.diag(_SVEC_SCALE), np.zeros((_Q, 3))]))
    offsets.append(np.zeros(_Q))
    whiten = whitening(shapes)
    # p_i / scale = linear_i x + t_hat / scale, with R X_i linear in Q
    linears = [
        np.hstack([np.kron(np.eye(3), point[None]) @ _ROTATION_MAP, np.eye(3)])
        for point in keypoints_3d / scale
    ]
    origin = estimate.translation / scale
    for linear, center, w in zip(linears, centers, whiten, strict=True):
        cone = np.vstack([[0.0, 0.0, 1.0], w @ (camera[:2] - np.outer(center, camera[2]))])
        cone /= np.abs(cone).max()  # a positive scale keeps the cone and evens the rows' magnitudes
        rows.append(-cone @ linear)
        offsets.append(cone @ origin)
    cuts = _depth_cuts(camera, keypoints_3d / scale, centers, shapes)
    for i, j, slope_i, slope_j, distance in cuts:  # slope_i z_i + slope_j z_j >= d_ij
        depth = slope_i * linears[i][2] + slope_j * linears[j][2]
        rows.append(-depth[None])
        offsets.append(np.array([(slope_i + slope_j) * origin[2] - distance]))
    reach = (_distance_bound(camera, keypoints_3d, centers, shapes) + scale) / scale
    return _Program(np.vstack(rows), np.concatenate(offsets), len(centers), len(cuts), scale, reach)


def _with_minors(program: _Program) -> _Program:
    """``program`` with Q's PSD cone replaced by its six 2x2 principal minors (a weaker relaxation,
    still valid: every rotation's Q = q q^T satisfies them). Within a wedge the sides hold Q near
    rank one, where the minors bound as tightly as the PSD cone in the median program and still prove
    99 % of the empty wedges empty, at about half of Clarabel's solve (no 4x4 eigen-decompositions
    per iteration)."""
    start, end = 1, 1 + _Q  # Q's PSD rows
    return replace(
        program,
        matrix=np.vstack([program.matrix[:start], _MINOR_ROWS, program.matrix[end:]]),
        offset=np.concatenate([program.offset[:start], np.zeros(len(_MINOR_ROWS)), program.offset[end:]]),
        minors=True,
    )


def _capped(program: _Program, cap: tuple[np.ndarray, float] | None) -> _Program:
    """The relaxation of one rotation cell: q_0^T Q q_0 >= cos^2(phi) (None: the whole space)."""
    if cap is None:
        return program
    centre, cosine_squared = cap
    row = -np.concatenate([_quadratic_form(centre), np.zeros(3)])[None]
    return replace(
        program,
        matrix=np.vstack([program.matrix, row]),
        offset=np.append(program.offset, -cosine_squared),
        cuts=program.cuts + 1,
    )


def _outer_to_triangle() -> np.ndarray:
    """(16, _Q): u^T Q w = (u w^T).ravel() @ this, over Q's upper triangle (unscaled): Q_ab's
    coefficient is u_a w_b + u_b w_a off the diagonal, u_a w_a on it."""
    mapping = np.zeros((4, 4, _Q))
    for column, (a, b) in enumerate(_TRIANGLE):
        mapping[a, b, column] = mapping[b, a, column] = 1.0
    return mapping.reshape(16, _Q)


_OUTER_TO_TRIANGLE = _outer_to_triangle()


def _bilinear_rows(u: np.ndarray, w: np.ndarray) -> np.ndarray:
    """u_k^T Q w_k for every row k of u and w (k, 4), as rows over Q's upper triangle (unscaled)."""
    return (u[:, :, None] * w[:, None, :]).reshape(len(u), 16) @ _OUTER_TO_TRIANGLE


def _quadratic_form(vector: np.ndarray) -> np.ndarray:
    """v^T Q v as a row over Q's upper triangle (unscaled entries)."""
    return np.array([vector[a] ** 2 if a == b else 2 * vector[a] * vector[b] for a, b in _TRIANGLE])


def _ray_slopes(camera: np.ndarray, centers: np.ndarray, shapes: np.ndarray):
    """Per set: whether it is bounded, s_i >= ||K^-1 (y, 1)|| over it, and its centre's normalised
    image coordinates and radius (semi-major axis / f)."""
    values = np.linalg.eigvalsh(shapes)
    bounded = values[:, 0] > 0
    inverse = np.linalg.inv(camera)
    rays = np.c_[centers, np.ones(len(centers))] @ inverse.T
    radius = np.where(bounded, 1.0 / np.sqrt(np.where(bounded, values[:, 0], 1.0)), np.inf)
    radius = radius * max(inverse[0, 0], inverse[1, 1])
    return bounded, np.linalg.norm(rays, axis=1) + radius, rays[:, :2], radius


def _depth_cuts(camera: np.ndarray, keypoints_3d: np.ndarray, centers: np.ndarray, shapes: np.ndarray):
    """Linear cuts valid on PURSE that keep the relaxation off the camera centre.

    A keypoint in set i lies on a ray p = z K^-1 (y, 1) with ||K^-1 (y, 1)|| <= s_i over the set, so
    ||p_i|| <= s_i z_i, and rigidity gives d_ij = ||p_i - p_j|| <= s_i z_i + s_j z_j. Without them the
    relaxation contains R = 0, t = 0 (every cone holds with equality at p = 0).
    """
    bounded, slopes, _, _ = _ray_slopes(camera, centers, shapes)
    kept = np.flatnonzero(bounded)
    return [  # a chain through the bounded sets: all pairs cost a fifth of each solve and tighten nothing
        (i, j, slopes[i], slopes[j], float(np.linalg.norm(keypoints_3d[i] - keypoints_3d[j])))
        for i, j in zip(kept[:-1], kept[1:], strict=True)
    ]


def _distance_bound(camera: np.ndarray, keypoints_3d, centers, shapes) -> float:
    """An upper bound on ||t|| over PURSE (inf when no two sets are apart).

    The rays through two disjoint sets i, j make an angle with sin >= gap_ij / (s_i s_j), gap_ij
    the distance between the sets in normalised image coordinates; p_j is on its ray, so
    d_ij = ||p_i - p_j|| >= ||p_i|| sin(angle) and ||t|| <= ||p_i|| + ||X_i||.
    """
    bounded, slopes, normalised, radius = _ray_slopes(camera, centers, shapes)
    best = math.inf
    for i in range(len(centers)):
        for j in range(len(centers)):
            if i == j or not (bounded[i] and bounded[j]):
                continue
            gap = float(np.linalg.norm(normalised[i] - normalised[j]) - radius[i] - radius[j])
            if gap > 0:
                distance = float(np.linalg.norm(keypoints_3d[i] - keypoints_3d[j]))
                best = min(
                    best, distance * slopes[i] * slopes[j] / gap + float(np.linalg.norm(keypoints_3d[i]))
                )
    return best


@cache
def _cones(keypoints: int, cuts: int, minors: bool = False) -> tuple:
    clarabel = _clarabel()
    cones = [clarabel.ZeroConeT(1)]
    cones += [clarabel.SecondOrderConeT(3) for _ in range(6)] if minors else [clarabel.PSDTriangleConeT(4)]
    cones += [clarabel.SecondOrderConeT(3) for _ in range(keypoints)]
    return tuple(cones + ([clarabel.NonnegativeConeT(cuts)] if cuts else []))


def _project_dual(dual: np.ndarray, keypoints: int, cuts: int, minors: bool = False) -> np.ndarray:
    """The multipliers projected onto the dual cones (all self-dual; the zero cone's dual is free)."""
    projected = dual.copy()
    if minors:
        keypoints, start = keypoints + 6, 1
    else:
        matrix = np.zeros((4, 4))
        matrix[_UPPER] = matrix[_LOWER] = projected[1 : 1 + _Q] / _SVEC_SCALE
        values, vectors = np.linalg.eigh(matrix)
        matrix = (vectors * np.maximum(values, 0.0)) @ vectors.T
        projected[1 : 1 + _Q] = matrix[_UPPER] * _SVEC_SCALE
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
    primal: float  # the solver's optimal value of min q^T x
    lower: float  # our weak-duality lower bound on it (before the translation residual term)
    translation_residual: float  # || r_t ||: its coefficient on the translation offset
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


def _minimise(program: _Program, objective: np.ndarray, solver=None):
    if solver is None:
        solver = _solver(program, objective)
    else:
        solver.update(q=objective)
    return solver, _outcome(program, objective, solver.solve())


def _outcome(program: _Program, objective: np.ndarray, solution) -> _Solved:
    """What a solution proves, its certificate checked here (a stalled solve is retried)."""
    for options in _RETRIES:
        if _status(solution) in ("Solved", "PrimalInfeasible"):
            break
        # Clarabel sometimes stalls these programs at "AlmostSolved"; other settings solve them
        solution = _solver(program, objective, **options).solve()
    status = _status(solution)
    if status == "PrimalInfeasible":
        verified = _farkas_verified(program, np.asarray(solution.z))
        return _Solved(status, math.nan, -math.inf, math.inf, verified)
    if status != "Solved":
        return _Solved(status, math.nan, -math.inf, math.inf, False)
    dual = _project_dual(np.asarray(solution.z), program.keypoints, program.cuts, program.minors)
    residual = objective + program.matrix.T @ dual
    # q^T x = -b^T z + z^T s + r^T x >= -b^T z + r_Q^T x_Q + r_t^T x_t, z^T s >= 0; |Q_ab| <= 1
    lower = -float(program.offset @ dual) - float(np.abs(residual[:_Q]).sum())
    primal = float(objective @ np.asarray(solution.x))
    agrees = abs(primal - lower) <= _AGREEMENT * (1.0 + abs(primal))
    return _Solved(status, primal, lower, float(np.linalg.norm(residual[_Q:])), agrees)


def _farkas_verified(program: _Program, certificate: np.ndarray) -> bool:
    """Whether Clarabel's infeasibility certificate proves the relaxation empty.

    With z in the dual cones, every feasible x has 0 <= z^T s = b^T z - (A^T z)^T x; b^T z < 0 and
    A^T z = 0 make that impossible. Q's part of A^T z is bounded exactly (|Q_ab| <= 1); the
    translation part must vanish to rounding (1e-9 of |b^T z|): t has no a-priori bound.
    """
    z = _project_dual(certificate, program.keypoints, program.cuts, program.minors)
    gap = float(program.offset @ z)
    residual = program.matrix.T @ z
    margin = -gap - float(np.abs(residual[:_Q]).sum()) - float(np.linalg.norm(residual[_Q:])) * program.reach
    return bool(gap < 0 and margin > 0)


def _infeasible(status: str) -> bool:
    return status == "PrimalInfeasible"


def _empty(verified: bool) -> OuterBound:
    if verified:
        return OuterBound(True, "relaxation infeasible: no pose is consistent with the sets", empty=True)
    return OuterBound(False, "relaxation reported infeasible, certificate not verified")


@dataclass(frozen=True)
class _CellBound:
    """What the relaxation of one rotation cell proves (all in the program's scaled units)."""

    status: str  # "bounded", "empty" (infeasibility verified) or why it failed
    extents: np.ndarray | None = None  # (6,) upper bounds on +-e_k^T (t - t_hat) / scale
    smallest_trace: float = math.nan  # lower bound on tr(R_hat^T R)
    verified: bool = False


def _objectives(estimate: Pose, frame: np.ndarray) -> list[np.ndarray]:
    """The seven objectives: min -(+-e_k)^T dt for the ray frame's axes, then min tr(R_hat^T R)."""
    translation = [np.concatenate([np.zeros(_Q), -sign * axis]) for axis in frame for sign in (1.0, -1.0)]
    return [*translation, np.concatenate([estimate.rotation.reshape(9) @ _ROTATION_MAP, np.zeros(3)])]


def _proven(program: _Program, objective: int, solved: _Solved) -> float:
    """The certified bound a solved program gives: an extent (scaled) or a rotation angle (radians)."""
    lower = solved.lower - solved.translation_residual * program.reach  # r_t^T x_t over PURSE
    if objective < 6:
        return -lower
    return math.acos(min(1.0, max(-1.0, (lower - 1.0) / 2.0)))


def _bound_cell(program: _Program, objectives: list[np.ndarray], cap) -> _CellBound:
    program, solver, values, verified = _capped(program, cap), None, [], True
    for k, objective in enumerate(objectives):
        solver, solved = _minimise(program, objective, solver)
        if _infeasible(solved.status):
            status = "empty" if solved.agrees else "infeasibility certificate not verified"
            return _CellBound(status, verified=solved.agrees)
        if solved.status != "Solved":
            kind = "translation" if k < 6 else "rotation"
            return _CellBound(f"{kind} program: {solved.status}")
        values.append(_proven(program, k, solved))
        verified = verified and solved.agrees
    smallest_trace = 1.0 + 2.0 * math.cos(values[6])
    return _CellBound("bounded", np.array(values[:6]), smallest_trace, verified)


def _posed(program: _Program) -> str | None:
    """Why the relaxation cannot certify anything, if so."""
    if not (np.isfinite(program.matrix).all() and np.isfinite(program.offset).all()):
        return "relaxation not posed: the data overflow (extreme camera matrix or sets)"
    if not math.isfinite(program.reach):
        return "no proven bound on ||t|| over PURSE (no two sets apart): nothing to certify with"
    return None


def outer_bound(
    estimate: Pose,
    camera: np.ndarray,
    keypoints_3d: np.ndarray,
    centers: np.ndarray,
    shapes: np.ndarray,
    sampled: list[Pose] | None = None,
    splits: int = 0,
    programs: int = 0,
) -> OuterBound:
    """Certified upper bounds on the rotation and translation error over PURSE (see the module doc).

    ``programs`` conic programs of best-first search over rotation wedges around the estimate
    (``_Search``) tighten the whole-space bounds; ``splits`` rounds of the older branch-and-bound
    over quaternion cells (cells.py) do too, at more cost (used when ``splits`` > 0).
    """
    if not relaxation_available():
        return OuterBound(False, "the pose extra (clarabel) is not installed")
    with np.errstate(all="ignore"):
        program = _program(estimate, camera, keypoints_3d, centers, shapes)
    problem = _posed(program)
    if problem is not None:
        return OuterBound(False, problem)
    objectives = _objectives(estimate, ray_frame(estimate.translation))
    root = _bound_cell(program, objectives, None)
    if root.status != "bounded":
        return _empty(root.verified) if root.status == "empty" else OuterBound(False, root.status)
    sampled = sampled or []
    if splits > 0:
        return _split_rounds(estimate, program, objectives, root, sampled, splits)
    bounds = np.append(root.extents, math.acos(min(1.0, max(-1.0, (root.smallest_trace - 1.0) / 2.0))))
    if programs <= 0:
        return _finish(estimate, program.scale, bounds, root.verified, sampled, "whole rotation space")
    search = _Search(_WedgePrograms(program, estimate.rotation, objectives), _reached(estimate, sampled))
    leaves = search.run(bounds, programs)
    if not leaves:
        return OuterBound(False, "every rotation cell proven empty, yet the estimate is in PURSE")
    bounds = np.max([leaf.bounds for leaf in leaves], axis=0)
    detail = f"{search.spent} programs, {len(leaves)} rotation cells"
    return _finish(estimate, program.scale, bounds, root.verified, sampled, detail)


def _finish(estimate, scale, bounds, verified, sampled, detail) -> OuterBound:
    rotation = math.degrees(bounds[6])
    translation = _radius(bounds, scale)
    certified = verified and _dominates(estimate, rotation, translation, sampled)
    status = "solved, certificate verified" if certified else "solved, certificate not verified"
    return OuterBound(certified, f"{status} ({detail})", rotation, translation)


def _radius(bounds: np.ndarray, scale: float) -> float:
    """The translation radius from the six extents (a box around the estimate)."""
    extents = bounds[:6].clip(min=0.0)
    return scale * math.sqrt(sum(max(extents[2 * k], extents[2 * k + 1]) ** 2 for k in range(3)))


def _reached(estimate: Pose, poses: list[Pose]) -> tuple[float, float] | None:
    """The largest (translation, rotation in radians) distances to poses known in PURSE, if any."""
    if not poses:
        return None
    translation = max(float(np.linalg.norm(p.translation - estimate.translation)) for p in poses)
    rotation = max(math.radians(rotation_angle_deg(estimate.rotation, p.rotation)) for p in poses)
    return translation, rotation


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
    """The relaxations of one search's wedges: the whole-space program plus a wedge's sides
    a_k^T Q b_k <= 0 (cells.Wedge, exact for the wedge's rotations, Q = q q^T), solved by one
    Clarabel solver whose data is updated per wedge (the sparsity stays: the sides' rows are kept
    dense), which halves the cost of setting up each small program."""

    def __init__(self, program: _Program, estimate: np.ndarray, objectives: list[np.ndarray]) -> None:
        program = _with_minors(program)
        self.program, self.objectives = program, objectives
        self._anchor = left_product(to_quaternion(estimate))
        sides = len(SIDES[0])
        # one program for every wedge: its sides' rows (the last ones) are rewritten in place per wedge
        self._restricted = replace(
            program,
            matrix=np.vstack([program.matrix, np.zeros((sides, _N))]),
            offset=np.append(program.offset, np.zeros(sides)),
            cuts=program.cuts + sides,
        )
        pattern = np.vstack([program.matrix != 0, np.tile(np.arange(_N) < _Q, (sides, 1))])
        self._rows, self._columns = np.nonzero(pattern.T)  # column-major: compressed columns
        self._data = self._restricted.matrix.T[self._rows, self._columns]
        self._on_sides = self._columns >= len(program.matrix)  # by column of Q, then by side
        self._solver = None

    def solve(self, wedge: Wedge, quantity: int) -> tuple[_Program, _Solved]:
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
        return restricted, _outcome(restricted, objective, self._solver.solve())


class _Search:
    """Best-first branch-and-bound over rotation wedges around the estimate (cells.Wedge).

    The whole-space rotation bound rho puts every rotation of PURSE within rho of R_hat; the wedge
    of Gibbs vectors |g| <= tan(rho / 2) is cut in eight again and again where a bound is
    attained. Each step proves one bound for the leaf attaining the loosest quantity (a wedge
    proven empty is dropped), or splits that leaf once its bound is proven; a leaf wholly farther
    than the current rotation bound holds no pose of PURSE and is dropped unsolved. It stops after
    ``programs`` conic programs, or once rotation and translation are within ROTATION_TOLERANCE
    and TRANSLATION_TOLERANCE of the poses reached in PURSE. At every step the bounds (the worst
    over the leaves) are valid.
    """

    def __init__(self, programs: _WedgePrograms, reached: tuple[float, float] | None) -> None:
        self.programs, self.reached, self.spent = programs, reached, 0

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
        restricted, solved = self.programs.solve(leaf.cell, quantity)
        if _infeasible(solved.status) and solved.agrees:
            return False
        if solved.status == "Solved" and solved.agrees:
            value = _proven(restricted, quantity, solved)
            if quantity == 6:
                value = min(value, leaf.cell.farthest_angle())
            leaf.bounds[quantity] = min(leaf.bounds[quantity], value)
        return True

    def _loosest(self, bounds: np.ndarray) -> int | None:
        """Which bound to tighten next: the largest extent or the rotation, whichever is further
        (relative to its tolerance) from the poses reached (alternately without any); None once
        both are within their tolerances."""
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


def _split_rounds(estimate, program, objectives, root, sampled, splits) -> OuterBound:
    """The older branch-and-bound: rounds of splitting the quaternion cells attaining a bound."""
    leaves = [(cell, None, root) for cell in root_cells()]
    for round_ in range(splits + 1):
        leaves = _evaluated(program, objectives, leaves)
        if isinstance(leaves, str):
            return OuterBound(False, leaves)
        if not leaves:
            return _empty(True)
        if round_ < splits:
            leaves = _split_the_worst(leaves)
    extents = np.max([bound.extents for _, bound, _ in leaves], axis=0)
    smallest_trace = min(bound.smallest_trace for _, bound, _ in leaves)
    rotation = math.acos(min(1.0, max(-1.0, (smallest_trace - 1.0) / 2.0)))
    verified = all(bound.verified for _, bound, _ in leaves)
    bounds = np.append(extents, rotation)
    return _finish(estimate, program.scale, bounds, verified, sampled, f"{len(leaves)} rotation cells")


def _evaluated(program, objectives, leaves):
    """Every leaf with its bound (cells proven empty dropped), or the reason one failed.

    A leaf is (cell, bound or None, its parent's bound or None): a cell whose program fails keeps
    its parent's bound, which holds for it too (the cell lies in its parent).
    """
    done = []
    for cell, bound, parent in leaves:
        if bound is None:
            bound = _bound_cell(program, objectives, cell.cap())
        if bound.status == "empty":
            continue
        if bound.status != "bounded":
            if parent is None:
                return bound.status
            bound = parent
        done.append((cell, bound, None))
    return done


def _split_the_worst(leaves):
    """Split the cells that attain any of the seven bounds; keep the others with their bounds."""
    worst = {int(np.argmax([b.extents[k] for _, b, _ in leaves])) for k in range(6)}
    worst.add(int(np.argmin([b.smallest_trace for _, b, _ in leaves])))
    kept = [leaf for i, leaf in enumerate(leaves) if i not in worst]
    return kept + [(child, None, leaves[i][1]) for i in sorted(worst) for child in leaves[i][0].split()]


def _dominates(estimate: Pose, rotation_deg: float, translation: float, sampled: list[Pose]) -> bool:
    slack = 1e-6
    return all(
        rotation_angle_deg(estimate.rotation, p.rotation) <= rotation_deg + slack
        and float(np.linalg.norm(p.translation - estimate.translation)) <= translation * (1 + slack) + slack
        for p in sampled
    )
