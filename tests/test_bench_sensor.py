import json
import subprocess
import sys
from pathlib import Path

import pytest

WORLD = str(Path(__file__).parent / "worlds" / "tiny.geojson")


@pytest.mark.fleet
def test_bench_sensor_reports_label_accuracy_and_lidar_corner_error():
    out = subprocess.run(
        [sys.executable, "-m", "agents", "bench", "sensor", "--worlds", WORLD, "--lidar-every",
         "3", "--json"],
        capture_output=True, text=True, timeout=120, check=True,
    )
    doc = json.loads(out.stdout.strip().splitlines()[-1])
    row = doc["worlds"][WORLD]
    assert row["scans"] > 10 and row["lidar_scans"] > 3
    # The corner sensor reports true labels (only p_fn/p_fp and noise disturb it).
    assert row["label_accuracy"] >= 0.99
    assert 0.9 <= row["corner_detection"] <= 1.0
    # Split-and-merge on 1 cm range noise: nominal corners within a few centimetres.
    assert row["lidar_nominal_error_m_p50"] < 0.02
    assert row["lidar_nominal_error_m_p95"] <= doc["tol_m"]
    assert row["lidar_detection"] > 0.8
