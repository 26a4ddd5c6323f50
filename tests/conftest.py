"""Test-wide settings.

Hypothesis profiles (``HYPOTHESIS_PROFILE`` picks one; pytest's ``--hypothesis-profile`` too):

* ``ci`` (the default, here and in CI): derandomized -- every run tries the same examples, so
  a green run here is a green run in CI, and an old bug does not fail CI at random when a new
  draw happens to find it. No example database; a failure prints its reproduction blob.
* ``explore``: random examples, ten times each test's ``max_examples``, failures kept in
  ``.hypothesis/`` and replayed first next time. For hunting bugs by hand, e.g.
  ``HYPOTHESIS_PROFILE=explore .venv/bin/python -m pytest -q -m "not slow" tests/test_merge.py``;
  add what it finds as an ``@example`` or a regression test.

A profile only gives defaults: a test's own ``@settings(max_examples=...)`` wins over it
(``explore`` then scales it, see ``pytest_collection_modifyitems``). The profile must be loaded
before the test modules are imported, because ``settings(...)`` and ``@given`` capture the
then-current default; pytest imports this file before them.
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
    print_blob=True,
    deadline=None,
    suppress_health_check=[HealthCheck.too_slow],
)
settings.register_profile(
    "explore",
    derandomize=False,
    print_blob=True,
    deadline=None,
    suppress_health_check=[HealthCheck.too_slow],
)
settings.load_profile(os.environ.get("HYPOTHESIS_PROFILE", "ci"))
_EXPLORE_FACTOR = 10


def pytest_collection_modifyitems(items: list[pytest.Item]) -> None:
    """Under ``explore``, each property test runs ten times its own ``max_examples``, randomly.

    Per-test ``@settings`` override a profile, and nearly every property test sets
    ``max_examples`` (and a few ``derandomize``), so the profile alone would not explore more.
    Hypothesis has no public way to change a decorated test's settings: this replaces the
    settings object ``@given`` reads (``_hypothesis_internal_use_settings``), and stops with a
    clear error if a hypothesis release renames it."""
    if settings.get_current_profile_name() != "explore":
        return
    done: set[int] = set()
    for item in items:
        fn = getattr(item, "obj", None)
        if not getattr(fn, "is_hypothesis_test", False) or id(fn) in done:
            continue
        done.add(id(fn))
        own = getattr(fn, "_hypothesis_internal_use_settings", None)
        if not isinstance(own, settings):
            raise pytest.UsageError("HYPOTHESIS_PROFILE=explore: this hypothesis release keeps a test's "
                                    "settings elsewhere; update tests/conftest.py")
        fn._hypothesis_internal_use_settings = settings(
            own, max_examples=own.max_examples * _EXPLORE_FACTOR, derandomize=False
        )


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
