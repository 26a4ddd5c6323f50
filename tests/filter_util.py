"""Putting a :class:`mapping.filter.WireframeFilter` in a given state, for tests.

Some tests start the filter from a map it did not build, or give it the pose uncertainty a long
drive would have left. The filter has no public way to take either yet (wanted: ``initial_maps``
and ``initial_covariance`` arguments of its constructor, or a ``restart(maps, covariance)``
method), so this module is the one place the tests write its private state; when the public
way exists, only this module changes.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from mapping.filter import WireframeFilter
from mapping.wireframe import Wireframe


def set_state(
    f: WireframeFilter, maps: Sequence[Wireframe] | None = None, covariance: np.ndarray | None = None
) -> None:
    """Replace the particles' maps (one map per particle) and/or the pose covariance (3 x 3)."""
    if maps is not None:
        if len(maps) != f.config.particles:
            raise ValueError(f"{len(maps)} maps for {f.config.particles} particles")
        f._particles = list(maps)
    if covariance is not None:
        cov = np.asarray(covariance, dtype=np.float64)
        if cov.shape != (3, 3):
            raise ValueError(f"covariance must be 3 x 3, got {cov.shape}")
        f._cov = cov.copy()
