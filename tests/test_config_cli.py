"""The filter's configuration on the command line: --params FILE, --set KEY=VALUE, wiremap config show."""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import pytest

from agents.cli import main
from agents.params import ConfigArgs, parse_toml, resolve, to_toml
from mapping.config import config_items, with_overrides
from mapping.filter import FilterConfig

WORLDS = Path(__file__).parent / "worlds"
TINY = str(WORLDS / "tiny.geojson")


def run_cli(argv: list[str], capsys: pytest.CaptureFixture[str]) -> tuple[int, str, str]:
    try:
        code = main(argv)
    except SystemExit as exc:  # argparse errors
        code = int(exc.code or 0)
    out, err = capsys.readouterr()
    return code, out, err


def one_line(err: str) -> str:
    lines = err.strip().splitlines()
    assert len(lines) == 1, err
    return lines[0]


def show(argv: list[str], capsys: pytest.CaptureFixture[str]) -> dict[str, Any]:
    code, out, err = run_cli(["config", "show", "--json", *argv], capsys)
    assert code == 0, err
    return json.loads(out)


# ---------------------------------------------------------------------- errors: exit 2, one line
@pytest.mark.parametrize(
    ("argv", "expected"),
    [
        (["--set", "compass.young_wieght=0"],
         "--set compass.young_wieght: unknown key (did you mean compass.young_weight?)"),
        (["--set", "young_weight=0"], "--set young_weight: unknown key (did you mean compass.young_weight?)"),
        (["--set", "compass=0"], "--set compass: a group of settings; set one of them, e.g. compass.enabled"),
        (["--set", "compass.young_weight=abc"],
         "--set compass.young_weight=abc: must be a number, got 'abc'"),
        (["--set", "compass.young_weight=2"],
         "--set compass.young_weight=2: young_weight must be a number within [0, 1]"),
        (["--set", "refine.enabled=maybe"], "--set refine.enabled=maybe: must be true or false, got 'maybe'"),
        (["--particles", "3", "--set", "particles=0"],
         "--set particles=0: particles must be an integer >= 1"),
    ],
)
@pytest.mark.parametrize(
    ("command", "prefix"),
    [
        (["config", "show"], "wiremap config: "),
        (["map", "--world", TINY, "--out", "OUT", "--quiet"], "wiremap map: "),
        (["bench", "accuracy", "--world", TINY, "--out", "OUT"], "wiremap bench accuracy: "),
    ],
)
def test_a_bad_set_is_one_line_and_exit_2_before_any_work(
    command: list[str], prefix: str, argv: list[str], expected: str, tmp_path: Path,
    capsys: pytest.CaptureFixture[str],
) -> None:
    out = tmp_path / "out"
    code, stdout, err = run_cli([str(out) if a == "OUT" else a for a in command] + argv, capsys)
    assert code == 2
    assert one_line(err).startswith(prefix + expected)
    assert not out.exists() and stdout == ""


@pytest.mark.parametrize(
    ("text", "expected"),
    [
        ("[compass]\nyoung_wieght = 0\n",
         "compass.young_wieght: unknown key (did you mean compass.young_weight?)"),
        ("[compass]\nyoung_weight = 'x'\n", "compass.young_weight = \"x\": must be a number, got 'x'"),
        ("[icp]\ngate_end = 5.0\n", "icp.gate_end = 5.0: ICPConfig.gate_end must not exceed gate_start"),
        ("particles = [1\n", "not valid TOML"),
        ("[particles]\nx = 1\n", "particles.x: unknown key"),
    ],
)
def test_a_bad_params_file_is_one_line_and_exit_2(
    text: str, expected: str, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    p = tmp_path / "p.toml"
    p.write_text(text)
    code, _, err = run_cli(["config", "show", "--params", str(p)], capsys)
    assert code == 2
    assert one_line(err).startswith(f"wiremap config: --params {p}: ")
    assert expected in one_line(err)


def test_missing_unreadable_and_binary_params_files(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    binary = tmp_path / "b.toml"
    binary.write_bytes(b"\xff\xfe\x00")
    for path, expected in [(tmp_path / "none.toml", "no such file"), (tmp_path, "is a directory"),
                           (binary, "not UTF-8")]:
        code, _, err = run_cli(["map", "--world", TINY, "--out", str(tmp_path / "o"), "--params",
                                str(path)], capsys)
        assert code == 2 and one_line(err) == (f"wiremap map: --params {path}: {expected}"
                                               + (" text" if "UTF" in expected else ""))
    code, _, err = run_cli(["config", "show", "--set", "no_equals_sign"], capsys)
    assert code == 2 and "expected GROUP.KEY=VALUE" in one_line(err)


def test_jointly_valid_settings_are_accepted_whatever_their_order(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    # gate_end alone above the default gate_start is refused; with gate_start raised it is fine
    cfg = show(["--set", "icp.gate_end=5", "--set", "icp.gate_start=6"], capsys)
    assert (cfg["icp.gate_start"], cfg["icp.gate_end"]) == (6.0, 5.0)
    p = tmp_path / "p.toml"
    p.write_text("[icp]\ngate_end = 5.0\ngate_start = 6.0\n")
    assert show(["--params", str(p)], capsys)["icp.gate_end"] == 5.0


def test_run_checks_the_settings_before_the_router_starts(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    out = tmp_path / "run"
    code, stdout, err = run_cli(["run", "--world", TINY, "--robots", "2", "--out", str(out),
                                 "--set", "loops.enabeld=false"], capsys)
    assert code == 2 and stdout == "" and not out.exists()
    assert one_line(err) == "wiremap run: --set loops.enabeld: unknown key (did you mean loops.enabled?)"


def test_robot_refuses_a_bad_setting_before_the_bus(capsys: pytest.CaptureFixture[str]) -> None:
    code, _, err = run_cli(["robot", "--id", "r1", "--world", TINY, "--start", "1,1,0", "--set",
                            "icp.huber=-1"], capsys)
    assert code == 2 and one_line(err).startswith("wiremap robot: --set icp.huber=-1: ")


# ---------------------------------------------------------------------- precedence
def test_precedence_defaults_file_flags_set(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    p = tmp_path / "p.toml"
    p.write_text("particles = 7\nmerge_threshold = 0.3\n[compass]\nyoung_weight = 0.2\n")
    base = show([], capsys)
    assert (base["particles"], base["merge_threshold"], base["compass.young_weight"]) == (10, 0.2, 0.05)
    assert show(["--params", str(p)], capsys)["particles"] == 7  # the file over the defaults
    cfg = show(["--params", str(p), "--particles", "4"], capsys)  # a flag over the file
    assert (cfg["particles"], cfg["merge_threshold"], cfg["compass.young_weight"]) == (4, 0.3, 0.2)
    cfg = show(["--params", str(p), "--particles", "4", "--set", "particles=5", "--set",
                "compass.young_weight=0"],
               capsys)  # --set over everything
    assert (cfg["particles"], cfg["compass.young_weight"]) == (5, 0.0)
    # the last --set wins
    assert show(["--set", "particles=2", "--set", "particles=3"], capsys)["particles"] == 3


def test_world_defaults_and_mutation_follow_the_particle_count(capsys: pytest.CaptureFixture[str]) -> None:
    museum = show(["--world", "museum"], capsys)
    assert (museum["particles"], museum["merge_threshold"], museum["mutate"]) == (6, 0.4, True)
    small = show(["--world", "paper-small"], capsys)
    assert (small["particles"], small["merge_threshold"]) == (10, 0.2)
    assert show(["--set", "particles=1"], capsys)["mutate"] is False
    assert show(["--particles", "1", "--set", "mutate=true"], capsys)["mutate"] is True


def test_recorded_overrides_are_those_of_the_file_and_set_that_took_effect(tmp_path: Path) -> None:
    from agents.mapping_run import filter_config_for

    cargs = ConfigArgs("p.toml", {"particles": 7, "compass.young_travel": "inf"},
                       {"icp.corner_labels": "1,0"})
    r = resolve(cargs, lambda ov: filter_config_for(10, 0.2, 8.0, overrides=ov),
                {"particles": ("--particles", 4)})
    assert r.config.particles == 4
    assert r.recorded == {"compass.young_travel": "inf", "icp.corner_labels": [1, 0]}  # particles: the flag's
    assert filter_config_for(10, 0.2, 8.0, overrides=r.overrides) == r.config


# ---------------------------------------------------------------------- TOML
def test_config_show_round_trips_through_params(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    argv = ["--world", "museum", "--set", "compass.young_weight=0", "--set", "compass.anchor=none",
            "--set", "compass.young_travel=inf", "--set", "icp.corner_labels=1", "--max-range", "6.5"]
    code, toml_text, err = run_cli(["config", "show", *argv], capsys)
    assert code == 0, err
    assert "[compass]\n" in toml_text and "young_weight = 0.0  # --set\n" in toml_text
    assert 'anchor = "none"  # --set\n' in toml_text and "max_range = 6.5  # --max-range\n" in toml_text
    p = tmp_path / "shown.toml"
    p.write_text(toml_text)
    assert show(["--params", str(p)], capsys) == show(argv, capsys)  # without --world: the file has it all
    code, again, _ = run_cli(["config", "show", "--params", str(p)], capsys)
    strip = [ln.split("  #")[0] for ln in toml_text.splitlines() if not ln.startswith("#")]
    assert [ln.split("  #")[0] for ln in again.splitlines() if not ln.startswith("#")] == strip


@dataclass(frozen=True)
class _Leaf:
    depth: int = 2
    scale: float | None = None


@dataclass(frozen=True)
class _Mid:
    name: str = 'a "quoted" name'
    labels: tuple[int, ...] = (1, 2)
    leaf: _Leaf = field(default_factory=_Leaf)


@dataclass(frozen=True)
class _Top:
    on: bool = False
    limit: float = float("inf")
    mid: _Mid = field(default_factory=_Mid)


def test_nested_groups_are_nested_tables_and_read_back() -> None:
    cfg = with_overrides(_Top(), {"mid.leaf.depth": 5, "limit": 0.1 + 0.2})
    text = to_toml(config_items(cfg), header="a test")
    assert text.startswith("# a test\non = false\nlimit = 0.30000000000000004\n\n[mid]\n")
    assert "\n[mid.leaf]\ndepth = 5\nscale = \"none\"\n" in text
    back = parse_toml(text)
    assert back == {"on": False, "limit": 0.30000000000000004, "mid.name": 'a "quoted" name',
                    "mid.labels": [1, 2], "mid.leaf.depth": 5, "mid.leaf.scale": "none"}
    assert with_overrides(_Top(), back) == cfg


# ---------------------------------------------------------------------- the settings reach the filter
def test_bench_accuracy_set_reaches_the_filter_and_the_baseline(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch
) -> None:
    import mapping.filter as mf

    seen: list[FilterConfig] = []
    real = mf.WireframeFilter

    def spy(cfg: FilterConfig, *a: Any, **k: Any) -> Any:
        seen.append(cfg)
        return real(cfg, *a, **k)

    monkeypatch.setattr(mf, "WireframeFilter", spy)
    code, out, err = run_cli(["bench", "accuracy", "--world", TINY, "--seeds", "1", "--steps", "4",
                              "--baseline", "--particles", "3", "--set", "compass.young_weight=0", "--set",
                              "loops.enabled=false", "--out", str(tmp_path), "--json", "--quiet"], capsys)
    assert code == 0, err
    filt, base = seen
    assert ((filt.particles, filt.mutate, filt.compass.young_weight, filt.loops.enabled)
            == (3, True, 0.0, False))
    assert ((base.particles, base.mutate, base.compass.young_weight, base.loops.enabled)
            == (1, False, 0.0, False))
    summary = json.loads(out.splitlines()[-1])
    assert summary["particles"] == 3
    assert summary["config_overrides"] == {"compass.young_weight": 0.0, "loops.enabled": False}


def test_bench_accuracy_json_has_no_overrides_key_by_default(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    code, out, err = run_cli(["bench", "accuracy", "--world", TINY, "--seeds", "1", "--steps", "3",
                              "--out", str(tmp_path), "--json", "--quiet"], capsys)
    assert code == 0, err
    assert "config_overrides" not in json.loads(out.splitlines()[-1])


def test_map_records_the_overrides_and_follows_max_range(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    p = tmp_path / "p.toml"
    p.write_text("[compass]\nyoung_weight = 0.25\n")
    code, _, err = run_cli(["map", "--world", TINY, "--out", str(tmp_path / "m"), "--steps", "3", "--quiet",
                            "--params", str(p), "--set", "max_range=5", "--set", "particles=2"], capsys)
    assert code == 0, err
    report = json.loads((tmp_path / "m" / "report.json").read_text())
    assert report["particles"] == 2
    assert report["config_overrides"] == {"particles": 2, "max_range": 5.0, "compass.young_weight": 0.25}
    code, _, err = run_cli(["map", "--world", TINY, "--out", str(tmp_path / "d"), "--steps", "3",
                            "--quiet"], capsys)
    assert code == 0 and json.loads((tmp_path / "d" / "report.json").read_text())["config_overrides"] == {}


def test_robot_options_carry_the_settings_to_its_filter(tmp_path: Path) -> None:
    import argparse

    from agents.commands import robot
    from agents.mapping_run import robot_steps

    p = tmp_path / "p.toml"
    p.write_text("particles = 4\n[refine]\nenabled = false\n")
    parser = argparse.ArgumentParser()
    robot.add_arguments(parser)
    args = parser.parse_args(["--id", "r1", "--world", TINY, "--route", "1,1;4,1", "--duration", "1",
                              "--params", str(p), "--threshold", "0.3", "--set", "max_range=6"])
    opts = robot.options_from_args(args)
    assert (opts.particles, opts.threshold) == (4, 0.3)
    cfg = next(iter(robot_steps(opts))).filter.config
    assert (cfg.particles, cfg.merge_threshold, cfg.max_range, cfg.refine.enabled) == (4, 0.3, 6.0, False)
    defaults = robot.options_from_args(parser.parse_args(["--id", "r1", "--world", TINY, "--start", "1,1,0"]))
    assert (defaults.particles, defaults.threshold, defaults.filter_overrides) == (5, 0.2, {})


@pytest.mark.fleet  # opens the in-process Zenoh router
def test_run_hands_its_settings_to_every_robot(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch
) -> None:
    """``wiremap run`` starts each robot with the resolved particle count and a params.toml of
    the changed settings, and the fusion service with the merge threshold in effect (the fleet
    is not started: ``_start_fleet`` is replaced)."""
    from agents.commands import run as run_cmd
    from agents.errors import UserError

    seen: dict[str, Any] = {}

    def fake_start(procs: Any, args: Any, out: Path, ids: Any, routes: Any, threshold: float, bus: Any,
                   creds: Any, filter_args: list[str]) -> None:
        seen.update(threshold=threshold, filter_args=filter_args)
        raise UserError("stopped by the test")

    monkeypatch.setattr(run_cmd, "_start_fleet", fake_start)
    out = tmp_path / "run"
    code, _, err = run_cli(["run", "--world", TINY, "--robots", "1", "--out", str(out), "--no-progress",
                            "--particles", "3", "--set", "merge_threshold=0.25", "--set",
                            "compass.young_weight=0"],
                           capsys)
    assert code == 2 and "stopped by the test" in err
    assert seen["threshold"] == 0.25
    assert seen["filter_args"] == ["--particles", "3", "--params", str(out / "params.toml")]
    assert parse_toml((out / "params.toml").read_text()) == {
        "merge_threshold": 0.25, "compass.young_weight": 0.0
    }
