"""`wiremap bench register`'s 300-corner pairs (agents.bench.register, issue 20's speed target)."""

from __future__ import annotations

import pytest

from agents.bench import register as br


@pytest.mark.slow
def test_large_pairs_are_300_corner_museum_maps_that_register(capsys: pytest.CaptureFixture[str]) -> None:
    """Two pairs: the whole museum twice (281 corners each) and two overlapping halves of its
    coverage route (200+ corners each), in unrelated frames; both register within the success
    bounds, the summary has the JSON keys and the table its ``300 corners`` line."""
    pairs = br.large_pairs(2, 5, 0.03)
    assert [k for k, _, _ in pairs] == ["whole", "halves"]
    whole, halves = pairs[0], pairs[1]
    assert whole[1].wf.n_vertices == whole[2].wf.n_vertices == 281
    assert min(halves[1].wf.n_vertices, halves[2].wf.n_vertices) >= 200
    assert halves[1].wf.n_vertices < 281 and halves[2].wf.n_vertices < 281
    # Unrelated frames: the true transform between them is far from the identity.
    t = br._true_transform(whole[1], whole[2])
    assert abs(t.x) + abs(t.y) > 1.0
    rows = br.large_rows(pairs, repeats=1)
    assert all(r["accepted"] and r["success"] and not r["false_merge"] and r["ms"] > 0 for r in rows)
    summary = br.large_summary(rows)
    assert summary["pairs_300_corners"] == 2 and summary["success_300_corners"] == 2
    assert summary["false_merges_300_corners"] == 0
    assert summary["ms_per_attempt_300_corners_p50"] == pytest.approx(
        sorted(r["ms"] for r in rows)[0] / 2 + sorted(r["ms"] for r in rows)[1] / 2, rel=1e-3)
    assert br.large_summary([])["ms_per_attempt_300_corners_p50"] is None
    table = {"by_overlap": {}, **summary}
    br._print_table(table, [], rows)
    out = capsys.readouterr().out
    assert "300 corners" in out and "CPU ms p50" in out


def test_large_flag_wins_over_quick() -> None:
    """``--quick`` times 2 large pairs unless ``--large`` says otherwise (it used to override it)."""
    import argparse

    ap = argparse.ArgumentParser()
    br.add_arguments(ap)
    count = br.large_pair_count
    assert count(ap.parse_args([])) == br.LARGE_PAIRS
    assert count(ap.parse_args(["--quick"])) == 2
    assert count(ap.parse_args(["--quick", "--large", "6"])) == 6
    assert count(ap.parse_args(["--quick", "--large", "0"])) == 0
