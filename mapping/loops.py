"""Loop closure for the wireframe particle filter: a pose graph behind the maps.

The paper (Sec. IV-C) corrects each scan's pose against the map in view and leaves the map as
built. In a large world that is not enough: every wall enters the map at the pose of the scan
that first saw it, and the pose is only as good as the (younger, locally consistent) map it was
matched against, so heading errors of a few tenths of a degree pile up as the robot explores.
When the robot comes back, the scan matcher follows the young walls around it, the old ones sit
metres away, and the map keeps both (museum: 1.9 m mean error, recall 0.24). This module adds
what the paper does not have, a back end (choices written down here, tested in
``tests/test_loops.py``):

* **Keyframes.** Every ``spacing`` metres driven, the filter's pose estimate becomes a keyframe;
  the relative pose between consecutive keyframes, as estimated then, is an *odometry edge*
  whose covariance grows with the distance between them (``drift_xy``, ``drift_theta`` per
  square-root metre) plus, with ``motion_cov``, the part of the motion the scans did not pin
  down: each step's odometry noise fused with its accepted scan match's information
  (``(Q^-1 + H)^-1``, supplied by the filter to :meth:`LoopCloser.advance`). Tracking against
  walls in view keeps that small; a turn in an empty room, nothing within range, carries the
  odometry's full heading noise (degrees). The optimiser then bends the chain where the error
  was made instead of spreading a closure evenly along it (measurements: docs/experiments.md).
* **Birth of map corners.** Each corner of every particle is stamped with the keyframe current
  when it took its position (looked up by its exact coordinates: the merge never moves a corner
  it keeps, so a corner with coordinates not seen before has just been placed; a corner that
  :mod:`mapping.refine` moves is re-keyed by :meth:`LoopCloser.moved` and keeps its birth). A
  corner's position is only as good as the pose of that keyframe, and moves with it. The same
  table keeps each corner's observation count for :mod:`mapping.refine`.
* **Detection.** Every ``check_every`` metres, the scan is matched (the filter's ICP) against the
  *old* part of the best map only: the walls both of whose corners were born at least
  ``min_travel`` metres of driving ago. The prior is wide, the drift accumulated since those
  corners were born. Where young walls are in view too, the scan is also matched against them
  alone, and the loop's discrepancy is between the two poses: the tracking match uses the
  whole map, so by the time of the check it may already have pulled the pose onto the old
  walls (a corridor coming back to its start), while the young walls still sit where the
  drifted chain put them. A match that constrains at least ``min_constrained`` directions with a
  small residual and moves the pose by more than ``min_correction`` is a loop closure: a
  constraint between the keyframe where the matched corners were born (the median) and the
  current one.
* **Heading factors.** The filter's wall-direction compass (:mod:`mapping.compass`) measures
  the heading against the building's wall directions, an absolute reference. Each measurement
  (the part the filter's own update did not apply, :meth:`LoopCloser.heading`) becomes a factor
  on the next keyframe: a relative constraint to the fixed first keyframe with information on
  the heading only. Without them a closure that has to move the pose sideways does it largely by
  turning the chain (turning is cheap over a long lever), and the compass then fights the
  turned map.
* **Optimisation.** The pose graph (odometry edges, heading factors and every loop constraint
  so far, the first keyframe fixed) is solved by sparse nonlinear least squares (:func:`optimize`,
  Levenberg-Marquardt on the sparse normal equations).
* **Deformation.** Every particle's corners move with their birth keyframe,
  ``p' = K'_a K_a^{-1} p``; the pose estimate moves with the current keyframe. Walls that the
  robot mapped twice now lie on each other; each particle's young walls are merged into its old
  ones (:func:`mapping.merge.merge`, old as base), which removes the duplicates.

Everything is deterministic (no randomness); the filter calls :meth:`LoopCloser.after_step` at
the end of every step.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray
from scipy.sparse import csr_matrix, diags
from scipy.sparse.linalg import spsolve

from mapping.se2 import Pose, wrap_angles
from mapping.wireframe import Wireframe

__all__ = ["Closure", "LoopCloser", "LoopConfig", "optimize"]

FloatArray = NDArray[np.float64]
IntArray = NDArray[np.int64]
BoolArray = NDArray[np.bool_]


@dataclass(frozen=True)
class LoopConfig:
    """Parameters of :class:`LoopCloser`.

    Parameters
    ----------
    enabled : bool
        Run loop closure at all.
    spacing : float
        Metres driven between keyframes.
    min_travel : float
        A wall is *old* (a loop candidate) when both its corners were born at least this many
        metres of driving ago.
    check_every : float
        Metres driven between two loop checks.
    min_correction, min_rotation : float
        A match moving the pose by less than this (metres) and turning it by less than this
        (radians) is not worth a closure: the map is consistent there (defaults 0.05 m and
        0.1 degree: closures late are worse than small ones early; docs/experiments.md).
    drift_xy, drift_theta : float
        Odometry-edge standard deviation per square-root metre driven (metres, radians); also the
        width of the detection prior (``drift * sqrt(metres since the old corners' birth)``,
        at most ``max_prior_xy`` / ``max_prior_theta``).
    max_prior_xy, max_prior_theta : float
    min_constraints : int
        Fewest inlier constraint rows of a loop match.
    min_constrained : int
        Fewest well-constrained directions of a loop match (default 2: a corridor fixes the
        heading and the offset across it; the direction along it keeps the wide prior, so the
        constraint says nothing there).
    max_rmse : float
        Largest inlier RMS residual (metres) of a loop match.
    min_old_edges : int
        Fewest old walls in view for a check.
    motion_cov : bool
        Add the per-step covariances passed to :meth:`LoopCloser.advance` to the odometry
        edges (module docstring, "Keyframes").
    heading_factors : bool
        Keep the filter's absolute heading measurements (:meth:`LoopCloser.heading`, the
        wall-direction compass of :mod:`mapping.compass`) as factors on the keyframes, so that
        a closure does not turn a keyframe away from a heading the walls measured (module
        docstring, "Heading factors"; on: better maps over museum seeds 0-7, see
        docs/experiments.md).
    """

    enabled: bool = True
    spacing: float = 1.0
    min_travel: float = 40.0
    check_every: float = 2.0
    min_correction: float = 0.05
    min_rotation: float = math.radians(0.1)
    drift_xy: float = 0.05
    drift_theta: float = math.radians(0.1)
    max_prior_xy: float = 3.0
    max_prior_theta: float = math.radians(4.0)
    min_constraints: int = 4
    min_constrained: int = 2
    max_rmse: float = 0.05
    min_old_edges: int = 2
    motion_cov: bool = True
    heading_factors: bool = True

    def __post_init__(self) -> None:
        for name in ("spacing", "check_every", "drift_xy", "drift_theta", "max_prior_xy", "max_prior_theta",
                     "max_rmse"):
            v = getattr(self, name)
            if not (isinstance(v, (int, float)) and math.isfinite(v) and v > 0):
                raise ValueError(f"loop {name} must be a positive number, got {v!r}")
        for name in ("min_travel", "min_correction", "min_rotation"):
            v = getattr(self, name)
            if not (isinstance(v, (int, float)) and math.isfinite(v) and v >= 0):
                raise ValueError(f"loop {name} must be a number >= 0, got {v!r}")
        if not 1 <= self.min_constrained <= 3:
            raise ValueError(f"loop min_constrained must be 1, 2 or 3, got {self.min_constrained!r}")
        if self.min_constraints < 1 or self.min_old_edges < 1:
            raise ValueError("loop min_constraints and min_old_edges must be >= 1")


@dataclass(frozen=True)
class Closure:
    """One accepted loop closure: keyframes ``old`` and ``new``, the measured pose of ``new`` in
    ``old``'s frame, its information (3 x 3), and the pose correction it made."""

    old: int
    new: int
    relative: Pose
    information: FloatArray
    correction: Pose


def _rel(a: FloatArray, b: FloatArray) -> FloatArray:
    """Pose ``b`` in the frame of ``a`` (rows ``(x, y, theta)``), vectorised."""
    c, s = np.cos(a[:, 2]), np.sin(a[:, 2])
    dx, dy = b[:, 0] - a[:, 0], b[:, 1] - a[:, 1]
    return np.stack([c * dx + s * dy, -s * dx + c * dy, wrap_angles(b[:, 2] - a[:, 2])], axis=1)


def optimize(
    poses: FloatArray,
    edges: IntArray,
    measurements: FloatArray,
    sqrt_info: FloatArray,
    max_iterations: int = 20,
) -> FloatArray:
    """Least-squares pose graph: the poses (rows ``(x, y, theta)``, the first fixed) that best
    agree with the relative ``measurements`` (pose of ``edges[k, 1]`` in the frame of
    ``edges[k, 0]``), each residual whitened by its ``sqrt_info`` (k, 3, 3) (upper triangular
    ``S`` with ``S^T S`` the information). Analytic sparse Jacobian, Levenberg-Marquardt steps
    solved directly (``scipy.sparse.linalg.spsolve``), at most ``max_iterations``.

    Not ``scipy.optimize.least_squares``: with this sparse Jacobian (``trf``/``lsmr``) it is not
    bit-identical (different steps) and was 6x and 90x slower where both converged (square loops
    of tests/test_loops.py's kind, 41 and 401 keyframes: 187 vs 30 ms, 8.2 s vs 90 ms; medians).
    """
    n = len(poses)
    if n < 2 or len(edges) == 0:
        return poses.copy()
    a, b = edges[:, 0], edges[:, 1]
    x0 = poses[1:].reshape(-1)

    def full(x: FloatArray) -> FloatArray:
        return np.concatenate([poses[:1], x.reshape(-1, 3)])

    def residual(x: FloatArray) -> FloatArray:
        p = full(x)
        r = _rel(p[a], p[b]) - measurements
        r[:, 2] = wrap_angles(r[:, 2])
        out: FloatArray = np.einsum("kij,kj->ki", sqrt_info, r).reshape(-1)
        return out

    m = len(edges)
    rows = np.repeat(np.arange(3 * m).reshape(m, 3), 6, axis=1).reshape(m, 3, 6)  # (edge, row, 6 cols)
    cols = np.concatenate([3 * (a - 1)[:, None] + np.arange(3), 3 * (b - 1)[:, None] + np.arange(3)], axis=1)
    cols3 = np.broadcast_to(cols[:, None, :], (m, 3, 6))
    keep = np.broadcast_to(
        np.concatenate([np.repeat(a > 0, 3).reshape(m, 3), np.repeat(b > 0, 3).reshape(m, 3)],
                       axis=1)[:, None, :],
        (m, 3, 6)
    )

    def jacobian(x: FloatArray) -> csr_matrix:
        # d rel / d (pose a, pose b): rel_xy = R(-th_a) (t_b - t_a), rel_th = th_b - th_a.
        p = full(x)
        c, s_ = np.cos(p[a, 2]), np.sin(p[a, 2])
        d = p[b, :2] - p[a, :2]
        J = np.zeros((m, 3, 6))
        J[:, 0, 0], J[:, 0, 1], J[:, 1, 0], J[:, 1, 1] = -c, -s_, s_, -c
        J[:, 0, 2] = -s_ * d[:, 0] + c * d[:, 1]
        J[:, 1, 2] = -c * d[:, 0] - s_ * d[:, 1]
        J[:, 0, 3], J[:, 0, 4], J[:, 1, 3], J[:, 1, 4] = c, s_, -s_, c
        J[:, 2, 2], J[:, 2, 5] = -1.0, 1.0
        W = np.einsum("kij,kjl->kil", sqrt_info, J)
        return csr_matrix((W[keep], (rows[keep], cols3[keep])), shape=(3 * m, 3 * (n - 1)))

    # Levenberg-Marquardt with a sparse direct solve of the normal equations (SuperLU): the
    # graph is a chain plus a few loops, so J^T J is banded with a few off-band blocks.
    x = x0.copy()
    r = residual(x)
    cost = float(r @ r)
    lam = 1e-6
    for _ in range(max_iterations):
        J = jacobian(x)
        H = (J.T @ J).tocsc()
        g = J.T @ r
        diag = H.diagonal()
        step = spsolve(H + diags(lam * np.maximum(diag, 1e-9)).tocsc(), -g)
        if not np.all(np.isfinite(step)):
            lam *= 10.0
            continue
        xn = x + step
        rn = residual(xn)
        cn = float(rn @ rn)
        if cn <= cost:
            x, r = xn, rn
            done = cost - cn <= 1e-12 * max(cost, 1.0) or float(np.max(np.abs(step))) < 1e-9
            cost = cn
            lam = max(lam / 10.0, 1e-12)
            if done:
                break
        else:
            lam *= 10.0
    sol_x = x
    out = full(sol_x)
    out[:, 2] = wrap_angles(out[:, 2])
    return out


def _keys(points: FloatArray) -> NDArray[np.complex128]:
    return points[:, 0] + 1j * points[:, 1]


class LoopCloser:
    """The back end of one :class:`mapping.filter.WireframeFilter` (module docstring).

    Parameters
    ----------
    config : LoopConfig
    start : Pose
        The filter's initial pose (the first keyframe).
    """

    def __init__(self, config: LoopConfig, start: Pose) -> None:
        self.config = config
        self.keyframes: list[FloatArray] = [np.array([start.x, start.y, start.theta])]
        self.kf_distance: list[float] = [0.0]
        self.odom: list[FloatArray] = []  # relative pose kf[i] -> kf[i+1] as estimated then
        self.odom_length: list[float] = []
        self.odom_cov: list[FloatArray] = []  # extra covariance of each odometry edge (motion_cov)
        self._since_cov = np.zeros((3, 3))
        self.headings: list[tuple[int, float, float]] = []  # (keyframe, absolute heading, variance)
        self._pending_heading: tuple[float, float] | None = None
        self.closures: list[Closure] = []
        self.distance = 0.0
        self._since_kf = 0.0
        self._since_check = 0.0
        self._known = np.zeros(0, dtype=np.complex128)  # sorted corner keys
        self._birth = np.zeros(0, dtype=np.int64)  # keyframe of each key
        self._count = np.zeros(0, dtype=np.int64)  # observations of each key (mapping.refine)
        self._pending: list[tuple[NDArray[np.complex128], int]] = []

    # ------------------------------------------------------------------ bookkeeping
    @property
    def current_keyframe(self) -> int:
        return len(self.keyframes) - 1

    def advance(self, pose: Pose, driven: float, increment: FloatArray | None = None) -> None:
        """Account for ``driven`` metres ending at ``pose`` (adds a keyframe every ``spacing``).

        ``increment`` (3 x 3, robot frame at ``pose``) is the covariance this step adds to the
        relative pose of the current odometry edge (``LoopConfig.motion_cov``)."""
        if increment is not None:
            dth = pose.theta - float(self.keyframes[-1][2])
            c, s_ = math.cos(dth), math.sin(dth)
            R = np.array([[c, -s_, 0.0], [s_, c, 0.0], [0.0, 0.0, 1.0]])
            self._since_cov = self._since_cov + R @ increment @ R.T
        self.distance += driven
        self._since_kf += driven
        self._since_check += driven
        if self._since_kf >= self.config.spacing:
            cur = np.array([pose.x, pose.y, pose.theta])
            rel = _rel(self.keyframes[-1][None, :], cur[None, :])[0]
            self.odom.append(rel)
            self.odom_length.append(self._since_kf)
            self.odom_cov.append(self._since_cov)
            self._since_cov = np.zeros((3, 3))
            self.keyframes.append(cur)
            self.kf_distance.append(self.distance)
            self._since_kf = 0.0
            if self._pending_heading is not None:
                rest, var = self._pending_heading
                self.headings.append((len(self.keyframes) - 1, float(cur[2]) + rest, var))
                self._pending_heading = None

    def heading(self, rest: float, variance: float) -> None:
        """An absolute heading measurement at the current step: the measured heading minus the
        pose's heading after the filter fused it (``rest``, radians) and its variance. It becomes
        a factor on the next keyframe (``heading_factors``); a later measurement before that
        keyframe replaces it."""
        if self.config.heading_factors:
            self._pending_heading = (float(rest), float(variance))

    def _lookup(self, points: FloatArray) -> tuple[IntArray, BoolArray]:
        self._flush()
        k = _keys(points)
        if len(self._known) == 0:
            return np.zeros(len(k), dtype=np.int64), np.zeros(len(k), dtype=bool)
        i = np.clip(np.searchsorted(self._known, k), 0, len(self._known) - 1)
        return i, self._known[i] == k

    def births(self, points: FloatArray) -> IntArray:
        """Birth keyframe of each corner (-1 where unknown)."""
        i, found = self._lookup(points)
        return np.where(found, self._birth[i] if len(self._birth) else -1, -1)

    def age(self, points: FloatArray) -> float:
        """Metres driven since these corners were born: since the median of their birth
        keyframes (corners of unknown birth left out); 0 when none is known."""
        born = self.births(points)
        born = born[born >= 0]
        if len(born) == 0:
            return 0.0
        return float(self.distance - np.median(np.asarray(self.kf_distance)[born]))

    def counts(self, points: FloatArray) -> IntArray:
        """Observations of each corner so far (:mod:`mapping.refine`; 1 where unknown)."""
        i, found = self._lookup(points)
        return np.where(found, self._count[i] if len(self._count) else 1, 1)

    def moved(self, old: FloatArray, new: FloatArray, counts: IntArray) -> None:
        """Corners refined from ``old`` to ``new`` coordinates (:mod:`mapping.refine`): the new
        keys keep the old ones' births (the current keyframe where unknown) and take ``counts``.
        The old keys stay known until :meth:`prune` (another particle may still have them)."""
        if len(old) == 0:
            return
        b = self.births(old)
        b = np.where(b < 0, self.current_keyframe, b)
        keys = np.concatenate([_keys(new), self._known])
        births = np.concatenate([b, self._birth])
        cnt = np.concatenate([np.asarray(counts, dtype=np.int64), self._count])
        self._set_table(keys, births, cnt)  # the refined entries win

    def warped(self, pairs: Sequence[tuple[FloatArray, FloatArray]]) -> None:
        """Every particle's corners moved at once, ``(old, new)`` coordinates per particle (a
        map carried along with a pose graph: :meth:`mapping.filter.WireframeFilter.warp`): each
        known corner keeps its birth and count under its new key, and the old keys are dropped
        (no particle has them any more). The keyframes are not moved."""
        keys: list[NDArray[np.complex128]] = []
        births: list[IntArray] = []
        counts: list[IntArray] = []
        for old, new in pairs:
            b = self.births(old)
            known = b >= 0
            keys.append(_keys(new)[known])
            births.append(b[known])
            counts.append(self.counts(old)[known])
        if keys:
            self._set_table(np.concatenate(keys), np.concatenate(births), np.concatenate(counts))

    def _set_table(self, keys: NDArray[np.complex128], births: IntArray, counts: IntArray) -> None:
        """The corner table: each key once, with the birth and count of its first entry."""
        keys, first = np.unique(keys, return_index=True)
        self._known, self._birth, self._count = keys, births[first], counts[first]

    def stamp(self, particles: Sequence[Wireframe]) -> None:
        """Stamp the corners of ``particles`` not seen before with the current keyframe.

        All particles' corners are looked up at once: every new corner gets the same keyframe
        and count, so one stamp of their union leaves the same keys, births and counts as one
        stamp per particle did (the particles share most of their corners)."""
        seen: set[int] = set()
        points: list[FloatArray] = []
        for p in particles:
            if id(p) in seen or p.n_vertices == 0:
                continue
            seen.add(id(p))
            points.append(p.points)
        if points:
            allp = np.concatenate(points)
            new = np.unique(_keys(allp[self.births(allp) < 0]))
            if len(new):
                self._pending.append((new, self.current_keyframe))
        self._flush()

    def _flush(self) -> None:
        if not self._pending:
            return
        keys = np.concatenate([self._known] + [k for k, _ in self._pending])
        births = np.concatenate([self._birth]
                                + [np.full(len(k), b, dtype=np.int64) for k, b in self._pending])
        cnt = np.concatenate([self._count] + [np.ones(len(k), dtype=np.int64) for k, _ in self._pending])
        self._pending = []
        self._set_table(keys, births, cnt)  # keeps the first stamp of a key

    def prune(self, particles: Sequence[Wireframe]) -> None:
        """Forget the corners no particle has any more."""
        self._flush()
        if not len(self._known):
            return
        alive = np.unique(np.concatenate([_keys(p.points) for p in particles] + [np.zeros(0, np.complex128)]))
        keep = np.isin(self._known, alive)
        self._known, self._birth, self._count = self._known[keep], self._birth[keep], self._count[keep]

    # ------------------------------------------------------------------ detection
    def due(self) -> bool:
        """Whether a loop check is due (``check_every`` metres since the last one)."""
        return self.config.enabled and self._since_check >= self.config.check_every

    def old_part(self, wf: Wireframe) -> tuple[Wireframe, IntArray]:
        """The walls of ``wf`` both of whose corners were born ``min_travel`` metres ago or
        earlier, and each corner's birth keyframe (of ``wf``)."""
        old, _, births = self.split(wf)
        return old, births

    def split(self, wf: Wireframe) -> tuple[Wireframe, Wireframe, IntArray]:
        """``wf`` as its old walls (:meth:`old_part`) and the rest (the young walls), and each
        corner's birth keyframe; restarts the ``check_every`` count."""
        self._since_check = 0.0
        births = self.births(wf.points)
        kd = np.asarray(self.kf_distance)
        old_v = (births >= 0) & (kd[np.maximum(births, 0)] <= self.distance - self.config.min_travel)
        keep = old_v[wf.edges[:, 0]] & old_v[wf.edges[:, 1]] if wf.n_edges else np.zeros(0, dtype=bool)
        return wf.subgraph_edges(keep), wf.subgraph_edges(~keep), births

    def prior(self, born_kf: int) -> FloatArray:
        """Detection prior for corners born at keyframe ``born_kf``."""
        cfg = self.config
        d = max(self.distance - self.kf_distance[born_kf], 1.0)
        sx = min(cfg.drift_xy * math.sqrt(d), cfg.max_prior_xy)
        st = min(cfg.drift_theta * math.sqrt(d), cfg.max_prior_theta)
        return np.diag([sx * sx, sx * sx, st * st])

    # ------------------------------------------------------------------ closing
    def close(
        self,
        pose: Pose,
        corrected: Pose,
        born_kf: int,
        covariance: FloatArray,
        particles: Sequence[Wireframe],
        merge: Callable[[Wireframe, Wireframe], Wireframe],
    ) -> tuple[Pose, list[Wireframe]]:
        """Add the loop constraint "the robot at ``pose`` is really at ``corrected`` relative to
        keyframe ``born_kf``", optimise, deform every particle and merge its young walls into its
        old ones. Returns the new pose estimate and particles (identical inputs share outputs)."""
        cur = self.current_keyframe
        kf = np.asarray(self.keyframes)
        # The measurement: the current keyframe in born_kf's frame, as the corrected pose says.
        at_cur = Pose(*kf[cur]).inverse().compose(pose)  # pose relative to its keyframe
        cur_corr = corrected.compose(at_cur.inverse())
        rel = _rel(kf[born_kf][None, :], np.array([[cur_corr.x, cur_corr.y, cur_corr.theta]]))[0]
        cov = np.array(covariance, dtype=np.float64) + np.diag([0.02**2, 0.02**2, math.radians(0.1) ** 2])
        info = np.asarray(np.linalg.inv(0.5 * (cov + cov.T)), dtype=np.float64)
        self.closures.append(Closure(born_kf, cur, Pose(*rel), info, pose.inverse().compose(corrected)))
        new_kf = self._solve(kf)
        # Deform: each corner moves with its birth keyframe.
        out: dict[int, Wireframe] = {}
        moved_keys: list[tuple[NDArray[np.complex128], IntArray, IntArray]] = []
        split = self.distance - self.config.min_travel
        kd = np.asarray(self.kf_distance)
        for p in particles:
            if id(p) in out:
                continue
            if p.n_vertices == 0:
                out[id(p)] = p
                continue
            b = self.births(p.points)
            b = np.where(b < 0, cur, b)
            local = _rel(kf[b], np.column_stack([p.points, np.zeros(len(b))]))[:, :2]
            c, s = np.cos(new_kf[b, 2]), np.sin(new_kf[b, 2])
            pts = np.column_stack(
                [new_kf[b, 0] + c * local[:, 0] - s * local[:, 1],
                 new_kf[b, 1] + s * local[:, 0] + c * local[:, 1]]
            )
            moved = p.replace(points=pts)
            moved_keys.append((_keys(pts), b, self.counts(p.points)))
            # Young walls (a corner born within the last min_travel metres: the walls mapped
            # again on coming back) merged into the old ones.
            young_v = kd[b] > split
            young_e = (young_v[moved.edges[:, 0]] | young_v[moved.edges[:, 1]] if moved.n_edges
                       else np.zeros(0, bool))
            if young_e.any() and (~young_e).any():
                moved = merge(moved.subgraph_edges(~young_e), moved.subgraph_edges(young_e))
            out[id(p)] = moved
        # Re-key the births: deformed coordinates keep their corner's birth; corners the merge
        # created are stamped by the caller's next :meth:`stamp` (current keyframe).
        if moved_keys:
            keys = np.concatenate([m for m, _, _ in moved_keys])
            births = np.concatenate([bb for _, bb, _ in moved_keys])
            cnt = np.concatenate([cc for _, _, cc in moved_keys])
            self._set_table(keys, births, cnt)
        self.keyframes = [row.copy() for row in new_kf]
        new_pose = Pose(*new_kf[cur]).compose(at_cur)
        return new_pose, [out[id(p)] for p in particles]

    def _solve(self, kf: FloatArray) -> FloatArray:
        cfg = self.config
        n = len(kf)
        edges = [(i, i + 1) for i in range(n - 1)] + [(c.old, c.new) for c in self.closures]
        meas = list(self.odom) + [np.array([c.relative.x, c.relative.y, c.relative.theta])
                                  for c in self.closures]
        d = np.maximum(np.asarray(self.odom_length, dtype=np.float64), 0.1)
        if cfg.motion_cov and len(d):
            # One stacked inverse and Cholesky factor for all odometry edges.
            C = np.zeros((len(d), 3, 3))
            C[:, 0, 0] = C[:, 1, 1] = cfg.drift_xy**2 * d
            C[:, 2, 2] = cfg.drift_theta**2 * d
            C = C + np.asarray(self.odom_cov, dtype=np.float64)
            odo = np.linalg.cholesky(np.linalg.inv(0.5 * (C + C.transpose(0, 2, 1)))).transpose(0, 2, 1)
        else:
            odo = np.zeros((len(d), 3, 3))
            odo[:, 0, 0] = odo[:, 1, 1] = 1.0 / (cfg.drift_xy * np.sqrt(d))
            odo[:, 2, 2] = 1.0 / (cfg.drift_theta * np.sqrt(d))
        loops = [np.linalg.cholesky(c.information).T for c in self.closures]
        sq = np.concatenate([odo, np.asarray(loops, dtype=np.float64).reshape(-1, 3, 3)])
        if cfg.heading_factors and self.headings:
            # An absolute heading is a relative one to the fixed first keyframe, with no
            # information on the position (zero rows).
            cols = np.array(self.headings, dtype=np.float64)  # (keyframe, heading, variance) rows
            hk, ht, hv = cols[:, 0].astype(np.int64), cols[:, 1], cols[:, 2]
            edges += [(0, int(k)) for k in hk]
            hm = np.zeros((len(hk), 3))
            hm[:, 2] = wrap_angles(ht - kf[0, 2])
            meas += list(hm)
            hs = np.zeros((len(hk), 3, 3))
            hs[:, 2, 2] = 1.0 / np.sqrt(hv)
            sq = np.concatenate([sq, hs])
        return optimize(kf, np.asarray(edges, dtype=np.int64), np.asarray(meas), sq)
