"""``wiremap map`` end to end, the mapping loop, and the accuracy/speed benchmarks (short runs)."""

import json
import math
from pathlib import Path

import numpy as np
import pytest

from agents.cli import main
from mapping import Wireframe

WORLDS = Path(__file__).parent / "worlds"


def read_outputs(out: Path):
    wf = Wireframe.from_geojson(json.loads((out / "map.geojson").read_text()))
    rows = [line.split("\t") for line in (out / "trajectory.tsv").read_text().splitlines()]
    report = json.loads((out / "report.json").read_text())
    png = (out / "map.png").read_bytes()
    return wf, rows, report, png


def test_map_paper_small_short_route(tmp_path, capsys):
    out = tmp_path / "run"
    assert main(["map", "--world", "paper-small", "--steps", "25", "--seed", "1", "--out", str(out)]) == 0
    wf, rows, report, png = read_outputs(out)
    assert wf.n_edges > 0
    assert len(rows) == 25 and all(len(r) == 4 for r in rows)
    t = np.array([[float(v) for v in r] for r in rows])
    assert np.all(np.diff(t[:, 0]) > 0)  # simulation time, one line per scan
    assert t[0, 0] == 0.0
    assert png[:8] == b"\x89PNG\r\n\x1a\n"
    assert report["world"] == "paper-small" and report["steps"] == 25 and report["particles"] == 10
    assert report["particle_bytes"] >= report["best_bytes"] == wf.paper_storage_bytes()
    assert set(report["metrics"]) == {"cell_error", "wall_precision", "wall_recall", "mean_dist_m",
                                      "p95_dist_m", "cell_error_note"}
    assert report["metrics"]["wall_precision"] > 0.9
    # --steps stopped the route early: a partial map has no cell error (the unexplored area would
    # count as error), as after Ctrl-C
    assert report["metrics"]["cell_error"] is None and "cut short" in report["metrics"]["cell_error_note"]
    assert report["pose_error_max_m"] < 0.15
    captured = capsys.readouterr()
    assert "wrote" in captured.out
    assert "step 25 of 25" in captured.err  # the live progress line


def test_map_world_file_with_lidar(tmp_path):
    out = tmp_path / "lidar"
    args = ["map", "--world", str(WORLDS / "angled.geojson"), "--sensor", "lidar", "--steps", "12",
            "--particles", "4", "--out", str(out), "--quiet"]
    assert main(args) == 0
    wf, rows, report, _ = read_outputs(out)
    assert report["sensor"] == "lidar" and report["world"] == "angled"
    assert len(rows) == 12 and wf.n_edges > 0
    assert report["metrics"]["wall_precision"] > 0.8


def _write_log(path: Path, steps: int, clutter: bool, dt: float = 0.5) -> list:
    """A CARMEN log of a lidar driving through the hall world at 0.5 m/s, a scan every ``dt``
    seconds, with people-like clutter."""
    from agents.files.carmen import LaserScan, write_carmen
    from agents.mapping_run import seeds_for
    from agents.sim.lidar import LidarConfig, raycast
    from agents.sim.motion import drive
    from agents.sim.route import plan_route
    from agents.sim.world import load_world

    world = load_world(WORLDS / "hall.geojson")
    rngs = seeds_for(5)
    route = plan_route(world, rngs["route"])
    cfg = LidarConfig(beams=181, fov=math.pi, max_range=10.0, sigma=0.01)
    scans, odom = [], None
    rng = np.random.default_rng(9)
    for st in drive(route, dt=dt, rng=rngs["drive"])[:steps]:
        odom = st.true_pose if odom is None else odom.compose(st.odometry)
        r = raycast(world.truth.segments(), st.true_pose, cfg, rngs["sensor"])
        if clutter:  # a few legs and glass dropouts: short returns and missing returns
            for _ in range(3):
                k = int(rng.integers(0, cfg.beams - 4))
                r[k : k + 3] = np.minimum(r[k : k + 3], rng.uniform(0.5, 3.0))
            r[rng.random(cfg.beams) < 0.03] = np.inf
        scans.append(LaserScan(100.0 + st.t, r, cfg.angles(), cfg.max_range, odom))
    write_carmen(path, scans, fov=cfg.fov, max_range=cfg.max_range)
    return scans


def test_map_carmen_log_with_clutter(tmp_path):
    log = tmp_path / "hall.log"
    scans = _write_log(log, 30, clutter=True)
    out = tmp_path / "carmen"
    assert main(["map", "--carmen", str(log), "--out", str(out), "--quiet"]) == 0
    wf, rows, report, _ = read_outputs(out)
    # a scan every 0.25 m: a dense log, thinned by the motion filter to one every 0.5 m
    assert report["scans_in_log"] == 30 and len(rows) == 30 - report["scans_left_out"] >= 12
    # t is the log's timestamp of each scan mapped
    kept = [s.t for s in scans if any(abs(s.t - float(r[0])) < 1e-6 for r in rows)]
    assert len(kept) == len(rows) and [float(r[0]) for r in rows] == pytest.approx(kept, abs=1e-6)
    assert report["metrics"] is None and report["sensor"] == "lidar"
    assert 0 < wf.n_vertices <= 5000  # the particle's vertex budget
    assert all(np.isfinite(float(v)) for r in rows for v in r)


def test_map_thins_a_dense_log_by_the_motion_filter(tmp_path, capsys):
    from agents.files.carmen import read_carmen
    from mapping.lidar_frontend import FrontendConfig, motion_filter

    log = tmp_path / "dense.log"
    _write_log(log, 80, clutter=False, dt=0.1)  # a scan every 5 cm: a 10 Hz lidar at walking pace
    limits = FrontendConfig()
    kept = motion_filter([s.odom for s in read_carmen(log)], limits.min_travel, limits.min_turn)
    assert 5 < len(kept) < 40
    assert main(["map", "--carmen", str(log), "--out", str(tmp_path / "a")]) == 0
    assert f"a dense log (80 scans): {len(kept)} mapped" in capsys.readouterr().err
    _, rows, report, _ = read_outputs(tmp_path / "a")
    times = [s.t for s in read_carmen(log)]
    assert [float(r[0]) for r in rows] == pytest.approx([times[k] for k in kept], abs=1e-6)  # those scans
    assert len(rows) == len(kept) and report["scans_in_log"] == 80
    assert report["scans_left_out"] == 80 - len(kept)
    # every scan, when asked; the motion filter's limits are settings too
    assert main(["map", "--carmen", str(log), "--out", str(tmp_path / "b"), "--quiet",
                 "--set", "frontend.dense_share=1"]) == 0
    _, rows, report, _ = read_outputs(tmp_path / "b")
    assert len(rows) == 80 and report["scans_left_out"] == 0
    assert report["lidar_settings"] == {"frontend.dense_share": "1"}
    assert main(["map", "--carmen", str(log), "--out", str(tmp_path / "c"), "--quiet",
                 "--set", "frontend.min_travel=0.25", "--steps", "40"]) == 0
    _, rows, report, _ = read_outputs(tmp_path / "c")  # the log's first 40 scans, then the filter
    assert report["scans_in_log"] == 40 and len(rows) == 40 - report["scans_left_out"] > len(kept) // 2


@pytest.mark.parametrize(
    "args, needle",
    [
        (["--world", "no-such-world"], "no-such-world"),
        (["--world", "paper-small", "--set", "slam.enabled=false"], "a real lidar's setting"),
        (["--carmen", str(Path(__file__).parent / "data" / "freiburg-101-head.log.gz"), "--set",
          "frontend.dense_share=2"], "dense_share"),
        (["--carmen", str(Path(__file__).parent / "data" / "freiburg-101-head.log.gz"), "--set",
          "frontend.no_such_key=2"], "no_such_key"),
        (["--carmen", "/nonexistent/log.txt"], "no such file"),
        (["--world", "paper-small", "--particles", "0"], "particles"),
        (["--world", "paper-small", "--steps", "0"], "steps"),
    ],
)
def test_map_user_errors_exit_2(tmp_path, capsys, args, needle):
    assert main(["map", *args, "--out", str(tmp_path / "x"), "--quiet"]) == 2
    err = capsys.readouterr().err
    assert needle in err and "Traceback" not in err


def test_bench_accuracy_json_and_table(tmp_path, capsys):
    args = ["bench", "accuracy", "--world", str(WORLDS / "tiny.geojson"), "--seeds", "1", "--steps", "12",
            "--baseline", "--json", "--quiet", "--out", str(tmp_path)]
    assert main(args) == 0
    lines = capsys.readouterr().out.strip().splitlines()
    summary = json.loads(lines[-1])
    keys = {"world", "sensor", "seeds", "particles", "cell_error", "wall_precision", "wall_recall",
            "mean_dist_m", "p95_dist_m", "particle_bytes", "steps", "updates_per_s"}
    assert keys <= set(summary)
    assert summary["steps"] == 12 and summary["particles"] == 10 and summary["world"] == "tiny"
    assert set(summary["baseline"]) >= keys - {"world", "sensor", "seeds"}
    assert any(line.startswith("median") for line in lines)
    assert len(list(tmp_path.glob("*.png"))) == 2


def test_bench_accuracy_lidar_reports_the_clean_and_the_realistic_lidar(tmp_path, capsys):
    """--sensor lidar: a row per sensor (a sensor column), the JSON's top level is the clean
    lidar's with the same keys as ever, "realistic" holds the realistic lidar's medians; a PNG
    per sensor; --lidar-set reaches the realistic lidar and a bad key is a user error."""
    args = ["bench", "accuracy", "--world", str(WORLDS / "tiny.geojson"), "--seeds", "1", "--steps", "6",
            "--sensor", "lidar", "--json", "--quiet", "--out", str(tmp_path)]
    assert main(args) == 0
    lines = capsys.readouterr().out.strip().splitlines()
    summary = json.loads(lines[-1])
    keys = {"cell_error", "wall_precision", "wall_recall", "mean_dist_m", "p95_dist_m", "particle_bytes",
            "steps", "updates_per_s"}
    assert summary["sensor"] == "lidar" and keys <= set(summary)
    assert summary["realistic"]["sensor"] == "lidar-real" and keys <= set(summary["realistic"])
    assert lines[0].split()[:3] == ["seed", "sensor", "method"]
    assert [ln.split()[1] for ln in lines[1:] if ln.startswith("median")] == ["lidar", "lidar-real"]
    assert sorted(p.name for p in tmp_path.glob("*.png")) == [
        "tiny-lidar-real-seed0-filter.png", "tiny-lidar-seed0-filter.png"]
    assert main([*args, "--lidar-set", "scene.people_per_100m2=0"]) == 0
    out = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    assert out["realistic"]["lidar_settings"] == {"scene.people_per_100m2": "0"}
    assert main([*args, "--lidar-set", "scene.no_such=1"]) == 2
    assert "--lidar-set" in capsys.readouterr().err


def test_bench_accuracy_wall_tolerance(tmp_path, capsys):
    """--wall-tol scores walls at that tolerance (the world-file target is 95 % at 0.2 m): the
    same map scores lower at 1 mm than at the default 0.4 m, the JSON says which tolerance it
    used, and a tolerance that is not a positive number is a user error."""
    common = ["bench", "accuracy", "--world", str(WORLDS / "tiny.geojson"), "--seeds", "1", "--steps", "12",
              "--json", "--quiet", "--out", str(tmp_path)]
    got = {}
    for tol in (None, "0.2", "0.001"):
        assert main([*common, *(["--wall-tol", tol] if tol else [])]) == 0
        got[tol] = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    assert "wall_tol_m" not in got[None] and got["0.2"]["wall_tol_m"] == 0.2
    assert got["0.001"]["wall_precision"] < got[None]["wall_precision"]
    assert got["0.001"]["wall_recall"] < got[None]["wall_recall"]
    assert got["0.2"]["mean_dist_m"] == got[None]["mean_dist_m"]  # the same map, scored otherwise
    for bad in ("0", "-1", "nan"):
        assert main([*common, "--wall-tol", bad]) == 2
        assert "--wall-tol" in capsys.readouterr().err


@pytest.mark.fleet
def test_bench_accuracy_jobs_give_the_same_maps(tmp_path, capsys):
    """Seeds run in worker processes (--jobs 2) give the same figures as one after another,
    in seed order, and every map's PNG."""
    common = ["bench", "accuracy", "--world", str(WORLDS / "tiny.geojson"), "--seeds", "2",
              "--first-seed", "3", "--steps", "10", "--json", "--quiet"]
    out = {}
    for jobs in ("1", "2"):
        assert main([*common, "--jobs", jobs, "--out", str(tmp_path / jobs)]) == 0
        lines = capsys.readouterr().out.strip().splitlines()
        out[jobs] = ([ln.split()[:7] for ln in lines if ln[:1].isdigit()], json.loads(lines[-1]))
        assert len(list((tmp_path / jobs).glob("*.png"))) == 2
    rows1, sum1 = out["1"]
    rows2, sum2 = out["2"]
    assert [r[0] for r in rows1] == ["3", "4"] and rows1 == rows2
    del sum1["updates_per_s"], sum2["updates_per_s"]
    assert sum1 == sum2
    assert main([*common, "--jobs", "0", "--out", str(tmp_path / "0")]) == 2


@pytest.mark.fleet
def test_bench_speed_medians_over_seeds(capsys):
    """--seeds K: one child per world and seed, a table row for each plus the median, and the
    JSON's figures are the medians (the ratio that of the two median step times)."""
    args = ["bench", "speed", "--steps", "4", "--museum-warmup", "2", "--seed", "1", "--seeds", "2", "--json"]
    assert main(args) == 0
    lines = capsys.readouterr().out.strip().splitlines()
    summary = json.loads(lines[-1])
    assert summary["seeds"] == 2
    for world, key in (("paper-small", "paper_small"), ("museum", "museum")):
        rows = [r for r in map(str.split, lines) if r[0] == world and (r[1].isdigit() or r[1] == "median")]
        assert [r[1] for r in rows] == ["1", "2", "median"]
        p50 = [float(r[3]) for r in rows[:2]]
        assert summary[key]["step_ms_p50"] == pytest.approx(np.median(p50), abs=0.006)
        assert set(summary[key]) == {"updates_per_s", "step_ms_p50", "step_ms_p95", "peak_rss_mb"}
    ratio = summary["museum"]["step_ms_p50"] / summary["paper_small"]["step_ms_p50"]
    # the summary's ratio is rounded to 3 decimals (within 5e-4 of the ratio of its medians)
    assert summary["museum_to_small_step_ratio"] == pytest.approx(ratio, rel=1e-3, abs=6e-4)
    assert main(["bench", "speed", "--seeds", "0"]) == 2


def test_speed_measure_keys():
    from agents.bench.speed import measure

    r = measure(str(WORLDS / "tiny.geojson"), particles=3, steps=8, warmup=2, seed=0)
    assert r["steps"] == 8
    assert r["updates_per_s"] > 0 and r["step_ms_p95"] >= r["step_ms_p50"] > 0 and r["peak_rss_mb"] > 0


@pytest.mark.slow
def test_speed_pieces_keys():
    """`wiremap bench speed --pieces`: the pieces whose speed tests no longer assert."""
    from agents.bench.speed import pieces
    from agents.sim.world import builtin_names

    r = pieces()
    assert set(r) == {"raycast_ms", "extract_ms", "evaluate_museum_ms", "render_museum_ms",
                      "codec_reject_claim_us", "plan_route_s"}
    assert set(r["plan_route_s"]) == set(builtin_names())
    assert all(v > 0 for v in [*r.values(), *r.pop("plan_route_s").values()] if not isinstance(v, dict))


def test_robot_steps_yield_the_robot_state():
    from agents.fleet.robot import RobotOptions, start_pose_of
    from agents.mapping_run import robot_steps

    route = np.array([[1.0, 1.0], [4.0, 1.0], [4.0, 3.0]])
    opts = RobotOptions(robot="r1", world=str(WORLDS / "tiny.geojson"), start=start_pose_of(route),
                        route=route, particles=3, seed=4, duration=3.0)
    steps = list(robot_steps(opts))
    assert len(steps) == 7  # t = 0, 0.5, ..., 3.0
    assert steps[0].filter.config.merge_threshold == opts.threshold != opts.resolution
    first, last = steps[0], steps[-1]
    assert first.pose.almost_equal(first.pose.identity())  # the map frame is the odometry frame
    assert first.true_pose.distance(opts.start) < 1e-9
    # the estimate (odometry frame) composed with the start matches the truth
    assert opts.start.compose(last.pose).distance(last.true_pose) < 0.1
    assert last.filter.best.n_edges > 0 and last.scan.n_vertices > 0
