"""Test-wide settings.

Under CI (``CI`` set), hypothesis is derandomized: every run explores the same examples, so a
green run here is a green run in CI (run ``CI=1 make test`` to reproduce it). Locally each run
draws new examples, which is how property tests keep finding bugs.
"""

import multiprocessing.process
import os
import subprocess

import pytest
import zenoh
from hypothesis import HealthCheck, settings

settings.register_profile(
    "ci",
    derandomize=True,
    database=None,
    deadline=None,
    suppress_health_check=[HealthCheck.too_slow],
)
settings.register_profile("dev", deadline=None, suppress_health_check=[HealthCheck.too_slow])
settings.load_profile("ci" if os.environ.get("CI") else "dev")


# ------------------------------------------------------------------------------------- lanes
# `make check` runs `pytest -m "not fleet and not slow"`: it must not start processes or
# routers. A test that does is marked `fleet` (the marker is declared in pyproject.toml). This
# guard keeps the marking honest: outside `fleet` tests, starting a subprocess, forking, or
# opening a Zenoh session (an in-process router included) fails the test with a message
# naming the marker, instead of quietly putting a multi-process test in the fast lane.
_PROCESS_STARTERS = (
    (subprocess.Popen, "__init__"),
    (os, "fork"),
    (os, "posix_spawn"),
    (multiprocessing.process.BaseProcess, "start"),
)


@pytest.fixture(autouse=True)
def _fleet_marker_is_honest(request: pytest.FixtureRequest, monkeypatch: pytest.MonkeyPatch) -> None:
    if request.node.get_closest_marker("fleet") is not None:
        return

    def refuse(*args: object, **kwargs: object) -> None:
        raise RuntimeError(f"{request.node.nodeid} starts a process or a Zenoh session: "
                           "mark it @pytest.mark.fleet")

    for owner, name in _PROCESS_STARTERS:
        monkeypatch.setattr(owner, name, refuse)
    monkeypatch.setattr(zenoh, "open", refuse)
