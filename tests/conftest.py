"""Test-wide settings.

Under CI (``CI`` set), hypothesis is derandomized: every run explores the same examples, so a
green run here is a green run in CI (run ``CI=1 make test`` to reproduce it). Locally each run
draws new examples, which is how property tests keep finding bugs.
"""

import os

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
