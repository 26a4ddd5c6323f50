"""The cheaper lidar SLAM of issue 17, part 3 (branch slamspeed), gives the same numbers bit for
bit: the pose graph's Gauss-Newton with its matrix assembled in a fixed summation order, and
the loop search's likelihood field from integer squared distances. Each is checked here against
the former formulation, kept in this file as the reference. The whole SLAM is checked by
``tests/lidar_cost.py`` on the CARMEN logs (same digests as before the change)."""

from __future__ import annotations

import math

import numpy as np
import pytest
import scipy.sparse as sp
import scipy.sparse.linalg as spla
from scipy.ndimage import distance_transform_edt

from mapping.lidar_slam import Edge, _edge_errors, _field_values, optimize


def optimize_reference(poses, edges, iterations=10, kernel=3.0):
    """The former :func:`optimize`: everything rebuilt every iteration, the matrix by
    ``scipy.sparse.csc_matrix((vals, (rows, cols)))``."""
    x = np.array(poses, dtype=np.float64)
    n = len(x)
    if n < 2 or not edges:
        return x
    ii = np.array([e.i for e in edges])
    jj = np.array([e.j for e in edges])
    z = np.array([e.z for e in edges])
    omega0 = np.array([e.omega for e in edges])
    robust = np.array([e.robust for e in edges])
    cz, sz = np.cos(z[:, 2]), np.sin(z[:, 2])
    r3, c3 = np.repeat(np.arange(3), 3), np.tile(np.arange(3), 3)
    for _ in range(iterations):
        err = _edge_errors(x, ii, jj, z)  # unchanged by the rewrite: shared
        xi, xj = x[ii], x[jj]
        ci, si = np.cos(xi[:, 2]), np.sin(xi[:, 2])
        dx, dy = xj[:, 0] - xi[:, 0], xj[:, 1] - xi[:, 1]
        c, s_ = np.cos(xi[:, 2] + z[:, 2]), np.sin(xi[:, 2] + z[:, 2])
        rt = np.stack([np.stack([c, s_], 1), np.stack([-s_, c], 1)], 1)
        ddx, ddy = -si * dx + ci * dy, -ci * dx - si * dy
        a = np.zeros((len(edges), 3, 3))
        a[:, :2, :2] = -rt
        a[:, 0, 2] = cz * ddx + sz * ddy
        a[:, 1, 2] = -sz * ddx + cz * ddy
        a[:, 2, 2] = -1.0
        b_ = np.zeros((len(edges), 3, 3))
        b_[:, :2, :2] = rt
        b_[:, 2, 2] = 1.0
        om = omega0.copy()
        if robust.any():
            chi2 = np.einsum("mi,mij,mj->m", err, omega0, err)
            om[robust] /= (1.0 + chi2[robust] / kernel**2)[:, None, None]
        rows, cols, vals = [], [], []
        b = np.zeros(3 * n)
        for (np_, jp) in ((ii, a), (jj, b_)):
            jto = np.einsum("mki,mkl->mil", jp, om)
            np.add.at(b, (3 * np_[:, None] + np.arange(3)).ravel(), np.einsum("mil,ml->mi", jto, err).ravel())
            for (nq, jq) in ((ii, a), (jj, b_)):
                blk = np.einsum("mil,mlq->miq", jto, jq)
                rows.append((3 * np_[:, None] + r3).ravel())
                cols.append((3 * nq[:, None] + c3).ravel())
                vals.append(blk.reshape(len(edges), 9).ravel())
        rows.append(np.arange(3))
        cols.append(np.arange(3))
        vals.append(np.full(3, 1e12))
        h = sp.csc_matrix((np.concatenate(vals), (np.concatenate(rows), np.concatenate(cols))),
                          shape=(3 * n, 3 * n))
        dxs = spla.spsolve(h, -b)
        x += dxs.reshape(-1, 3)
        x[:, 2] = (x[:, 2] + math.pi) % (2.0 * math.pi) - math.pi
        if float(np.abs(dxs).max()) < 1e-6:
            break
    return x


def random_graph(rng: np.random.Generator, n: int, extra: int, hub: bool) -> tuple[np.ndarray, list[Edge]]:
    """A chain of ``n`` noisy poses and ``extra`` random (robust or not) edges, some repeated,
    some on one hub node (many duplicates in one diagonal block: the unstable column sort)."""
    truth = np.cumsum(rng.normal(0, [0.5, 0.5, 0.2], (n, 3)), axis=0)
    truth[:, 2] = (truth[:, 2] + np.pi) % (2 * np.pi) - np.pi

    def edge(i: int, j: int, robust: bool) -> Edge:
        ci, si = math.cos(truth[i, 2]), math.sin(truth[i, 2])
        d = truth[j, :2] - truth[i, :2]
        z = np.array([ci * d[0] + si * d[1], -si * d[0] + ci * d[1], truth[j, 2] - truth[i, 2]])
        z += rng.normal(0, [0.05, 0.05, 0.02])
        z[2] = (z[2] + np.pi) % (2 * np.pi) - np.pi
        m = rng.normal(size=(3, 3))
        return Edge(i, j, z, m @ m.T + np.diag(rng.uniform(1, 100, 3)), robust)

    edges = [edge(k - 1, k, False) for k in range(1, n)]
    for _ in range(extra):
        i, j = sorted(rng.choice(n, 2, replace=False).tolist())
        edges.append(edge(0 if hub and rng.random() < 0.5 else i, j, bool(rng.random() < 0.7)))
    if extra:
        edges.append(edges[-1])  # the same pair twice
    poses = truth + rng.normal(0, [0.3, 0.3, 0.1], truth.shape)
    return poses, edges


@pytest.mark.parametrize("seed", range(12))
def test_optimize_is_the_former_formulation(seed: int) -> None:
    rng = np.random.default_rng(seed)
    n = int(rng.integers(2, 120))
    poses, edges = random_graph(rng, n, int(rng.integers(0, 3 * n)), hub=seed % 2 == 0)
    kernel = float(rng.uniform(1.0, 5.0))
    for iterations in (1, 10):
        new = optimize(poses, edges, iterations=iterations, kernel=kernel)
        old = optimize_reference(poses, edges, iterations=iterations, kernel=kernel)
        assert new.tobytes() == old.tobytes()


@pytest.mark.parametrize("seed", range(20))
def test_field_values_are_the_former_formulation(seed: int) -> None:
    rng = np.random.default_rng(seed)
    h, w = rng.integers(1, 200, 2)
    occ = rng.random((h, w)) > rng.choice([0.001, 0.02, 0.3, 0.9])
    occ.flat[rng.integers(occ.size)] = False
    res, sigma = float(rng.choice([0.05, 0.1, 0.13])), float(rng.uniform(0.05, 0.5))
    old = np.exp(-0.5 * ((distance_transform_edt(occ) * res) / sigma) ** 2)
    assert _field_values(occ, res, sigma).tobytes() == old.tobytes()
