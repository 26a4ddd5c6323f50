"""The fusion tree: regional fusers' partial maps merged by a root give the one-process map."""

from __future__ import annotations

import itertools
import time

import numpy as np
import pytest

from agents.errors import UserError
from agents.fleet.bus import FleetKeys
from agents.fleet.fusion import FusionConfig, FusionState, decode_message, encode_message
from agents.fleet.fusion.tree import (
    RobotSelector,
    RootState,
    fold_groups,
    fold_nodes,
    fold_ranges,
    is_fold_node,
    prefix_spans,
    remap_sources,
)
from tests.fleet_util import Fleet, FusedWatcher, client, in_process_router, query_stats, wait_until
from tests.tree_util import robot_views, tree_fuse

THR = 0.4


def _one_process(raws: dict[str, bytes], refine: bool = True) -> tuple[FusionState, object]:
    st = FusionState(FusionConfig(threshold=THR, refine=refine))
    for rid, raw in raws.items():
        st.offer(raw, rid)
    st.fuse(full=True)
    return st, decode_message(encode_message(st.fused_message(0)))


def _tree(raws: dict[str, bytes], groups: list[list[str]], refine: bool = True) -> tuple[RootState, object]:
    return tree_fuse(raws, groups, THR, refine)


def _same_map(a, b) -> None:
    assert a.robots == b.robots
    wa, wb = a.wireframe, b.wireframe
    assert (wa.n_vertices, wa.n_edges) == (wb.n_vertices, wb.n_edges)
    assert wa.almost_equal(wb, tol=1e-9, likelihood_tol=1e-9)
    assert np.array_equal(np.sort(wa.sources), np.sort(wb.sources))


def _is_same_map(ref):
    """A predicate for :meth:`FusedWatcher.wait_for`: the map is ``ref`` (:func:`_same_map`)."""

    def same(m) -> bool:
        try:
            _same_map(ref, m)
        except AssertionError:
            return False
        return True

    return same


# ---------------------------------------------------------------------- the fold's subtrees
def test_fold_nodes_are_subtrees_and_cover_the_fleet():
    for n in (1, 2, 3, 5, 16, 33, 48, 64):
        for k in (1, 2, 3, 4):
            spans = fold_nodes(n, k)
            assert spans[0][0] == 0 and spans[-1][1] == n
            assert all(a[1] == b[0] for a, b in itertools.pairwise(spans))
            assert all(is_fold_node(lo, hi, n) for lo, hi in spans)
    assert fold_nodes(64, 2) == [(0, 32), (32, 64)] and fold_nodes(48, 2) == [(0, 32), (32, 48)]
    assert not is_fold_node(0, 24, 48) and is_fold_node(32, 40, 48)
    assert prefix_spans(40, 48) == [(0, 32), (32, 40)] and prefix_spans(3, 4) == [(0, 2), (2, 3)]


def test_remap_sources_moves_each_bit():
    src = np.array([0b01, 0b10, 0b11, 0], dtype=np.uint64)
    out = remap_sources(src, [5, 63])
    assert out.tolist() == [1 << 5, 1 << 63, (1 << 5) | (1 << 63), 0]


def test_selectors():
    s = RobotSelector.parse("r0[1-4],r10")
    assert [r for r in ("r01", "r04", "r05", "r10", "r100") if s.matches(r)] == ["r01", "r04", "r10"]
    assert s.key_chunk() == "*" and RobotSelector.parse("r1*").key_chunk() == "r1$*"
    h = [RobotSelector.parse(f"hash:{i}/3") for i in range(3)]
    ids = [f"r{k}" for k in range(60)]
    assert sorted(r for s in h for r in ids if s.matches(r)) == sorted(ids)  # a partition


@pytest.mark.parametrize(("n", "k"), [(1, 2), (3, 2), (8, 2), (16, 4), (48, 2), (64, 3)])
def test_fold_ranges_take_the_subtrees_and_every_late_joiner_once(n, k):
    """``wiremap run --fusers K``'s patterns: each range takes exactly its subtree of the ids it
    was made from, and any other id (a robot that joins later) falls in exactly one range."""
    ids = [f"r{j + 1}" for j in range(n)]
    sels = [RobotSelector.parse(p) for p in fold_ranges(ids, k)]
    assert [[r for r in sorted(ids) if s.matches(r)] for s in sels] == fold_groups(ids, k)
    late = ["r0", "r1a", "r10b", "r99", "r100000", "a", "z", "R5", "r2-x", "r3.1", "_", "~"]
    for rid in late:
        assert sum(s.matches(rid) for s in sels) == 1, rid
    with pytest.raises(UserError):
        RobotSelector.parse("range:r5:r1")
    with pytest.raises(UserError):
        RobotSelector.parse("range:r/5:")


# ---------------------------------------------------------------------- the same map
@pytest.mark.parametrize(("n", "k"), [(3, 2), (16, 2), (16, 4), (24, 2), (32, 2)])
def test_tree_of_subtrees_gives_the_one_process_map(n, k):
    """Robot maps recorded once (views of the museum's walls with noise and start-pose error)
    fed to one FusionState and to a tree of k regional states and a root, partials through the
    codec: the same walls, robots and sources bits (compared as decoded, as a subscriber sees
    them; the codec does not keep vertex order)."""
    raws = {m.sender: encode_message(m) for m in robot_views("museum", n, seed=1)}
    _, ref = _one_process(raws)
    root, out = _tree(raws, fold_groups(list(raws), k))
    assert root.exact
    _same_map(ref, out)


def test_groups_that_are_not_subtrees_keep_provenance_but_say_so():
    raws = {m.sender: encode_message(m) for m in robot_views("museum", 12, seed=2)}
    ids = sorted(raws)
    groups = [[r for r in ids if RobotSelector.parse(f"hash:{i}/2").matches(r)] for i in range(2)]
    root, out = _tree(raws, groups)
    assert not root.exact and out.robots == tuple(ids)
    _, ref = _one_process(raws)
    # each wall's bits name robots of the fleet; every robot contributes somewhere
    seen = int(np.bitwise_or.reduce(out.wireframe.sources))
    assert seen == int(np.bitwise_or.reduce(ref.wireframe.sources)) == (1 << len(ids)) - 1


# ---------------------------------------------------------------------- over Zenoh
@pytest.mark.fleet
def test_seventy_robots_through_one_service_and_through_a_tree(tmp_path, record_property):
    """Past 64 robots on the bus: 70 robots' maps (with tokens) reach a one-process fusion
    service (fleet ``one``) and a tree of two regional fusers (64 + 6 robots) under a root
    (fleet ``tree``), all real processes; each publishes the one-process map of the 70 robots
    (format version 2, robots r65..r70 on bits 64..69)."""
    t0 = time.monotonic()
    raws = {m.sender: encode_message(m) for m in robot_views("museum", 70, seed=4, radius=10)}
    _, ref = _one_process(raws)
    assert len(ref.robots) == 70
    one, tree = FleetKeys("one"), FleetKeys("tree")
    with in_process_router() as ep, Fleet(tmp_path) as fleet, client(ep) as s:
        fleet.start("one", ["fuse", "--connect", ep, "--fleet", "one", "--threshold", repr(THR)])
        bus = ["--connect", ep, "--fleet", "tree", "--threshold", repr(THR)]
        fleet.start("g0", ["fuse", "--group", "g0", "--robots", "range::r65", *bus])
        fleet.start("g1", ["fuse", "--group", "g1", "--robots", "range:r65:", *bus])
        fleet.start("root", ["fuse", "--of-groups", "g0,g1", *bus])
        for name in ("one", "g0", "g1", "root"):
            fleet.wait_log(name, "ready", 60.0)
        tokens = [s.liveliness().declare_token(k.alive(r)) for k in (one, tree) for r in raws]
        watchers = {k.fleet: FusedWatcher(s, k) for k in (one, tree)}
        try:
            for k in (one, tree):
                for rid, raw in raws.items():
                    s.put(k.robot_map(rid), raw)

            same = _is_same_map(ref)

            for name, w in watchers.items():
                got = w.wait_for(same, 90.0, f"the one-process map of 70 robots ({name})")
                assert got.robots == tuple(sorted(raws)) and got.meta["stale"] == []
            stats = query_stats(s, one, 2.0)
            assert stats is not None and stats["stats"]["rejected"] == 0
        finally:
            for w in watchers.values():
                w.close()
            for t in tokens:
                t.undeclare()
        for name in ("one", "g0", "g1", "root"):
            assert fleet.stop(name, timeout=30) == 0, fleet.log(name)
            assert "Traceback" not in fleet.log(name)
    record_property("seventy_robots_wall_s", round(time.monotonic() - t0, 1))


@pytest.mark.fleet
def test_two_regional_fusers_and_a_root_publish_the_one_process_map(tmp_path):
    """A recorded fleet of 8 robots on the bus (each with its token), two regional fusers over
    the fold's two subtrees and a root as processes: the root's fused map (as a subscriber
    sees it) becomes the one-process full-path map of the same robot maps."""
    msgs = robot_views("museum", 8, seed=3)
    raws = {m.sender: encode_message(m) for m in msgs}
    _, ref = _one_process(raws)
    keys = FleetKeys("tree")
    with in_process_router() as ep, Fleet(tmp_path) as fleet, client(ep) as s:
        bus = ["--connect", ep, "--fleet", "tree", "--threshold", repr(THR)]
        fleet.start("g0", ["fuse", "--group", "g0", "--robots", "r0[1-4]", *bus])
        fleet.start("g1", ["fuse", "--group", "g1", "--robots", "r0[5-8]", *bus])
        fleet.start("root", ["fuse", "--of-groups", "g0,g1", *bus])
        for name in ("g0", "g1"):
            fleet.wait_log(name, "ready", 60.0)
        fleet.wait_log("root", "root fuser ready", 60.0)
        tokens = [s.liveliness().declare_token(keys.alive(r)) for r in raws]
        watcher = FusedWatcher(s, keys)
        try:
            for rid, raw in raws.items():
                s.put(keys.robot_map(rid), raw)

            same = _is_same_map(ref)

            got = watcher.wait_for(same, 60.0, "the one-process map")
            assert got.meta["exact"] and got.meta["stale"] == []
            stats = wait_until(
                lambda: (d := query_stats(s, keys, 2.0)) and d["version"] >= got.seq and d, 10.0,
                "root stats of that version"
            )
            assert stats["role"] == "root" and stats["exact"] and set(stats["groups"]) == {"g0", "g1"}
            # a takeover of g1 started while g1 was only cut off (its partial with a newer boot):
            # g1, alive, takes a newer boot still and the root follows it again
            import dataclasses

            forged_boot = time.time_ns()
            forged = dataclasses.replace(
                got,
                sender="g1",
                robots=("r05",),
                seq=1,
                wireframe=got.wireframe.subgraph_edges(np.zeros(got.wireframe.n_edges, bool)),
                meta={"boot": forged_boot, "group": "g1", "select": "r0[5-8]"},
            )
            since = watcher.count()
            s.put("wiremap/tree/groups/g1/map",
                  encode_message(forged))
            back = watcher.wait_for(
                lambda m: m.meta["group_versions"].get("g1", [0])[0] > forged_boot and len(m.robots) == 8,
                20.0, "g1 taking its group back", since,
            )
            _same_map(ref, back)
            assert "taking it back" in fleet.log("g1")
        finally:
            watcher.close()
            for t in tokens:
                t.undeclare()


@pytest.mark.fleet
def test_a_killed_regional_fuser_is_taken_over_and_no_map_is_lost(tmp_path):
    """kill -9 of a regional fuser: the root keeps serving its last partial (flagged in
    ``fusers_down``), the other fuser takes its robots over from the bytes it kept, and a map a
    robot of the dead group sends after the kill reaches the fused map (timed). Restarted from
    its store, the fuser takes its group back (the takeover retires; newer boot at the root)."""
    msgs = robot_views("museum", 8, seed=4)
    keys = FleetKeys("tree2")
    with in_process_router() as ep, Fleet(tmp_path) as fleet, client(ep) as s:
        bus = ["--connect", ep, "--fleet", "tree2", "--threshold", repr(THR), "--no-refine"]
        fleet.start("g0", ["fuse", "--group", "g0", "--robots", "r0[1-4]", *bus])
        g1 = ["fuse", "--group", "g1", "--robots", "r0[5-8]", "--store", str(tmp_path / "store-g1"), *bus]
        fleet.start("g1", g1)
        fleet.start("root", ["fuse", "--of-groups", "*", *bus])
        for name in ("g0", "g1", "root"):
            fleet.wait_log(name, "ready", 60.0)
        tokens = [s.liveliness().declare_token(keys.alive(m.sender)) for m in msgs]
        watcher = FusedWatcher(s, keys)
        try:
            for m in msgs:
                s.put(keys.robot_map(m.sender), encode_message(m))
            full = watcher.wait_for(lambda m: len(m.robots) == 8, 60.0, "8 robots")
            fleet.kill9("g1")
            down = watcher.wait_for(lambda m: m.meta.get("fusers_down") == ["g1"], 10.0, "g1 down", 0)
            assert down.robots == full.robots  # the last partial is still served
            wait_until(lambda: "taking over" in fleet.log("g0"), 10.0, "g0 takes over g1")
            # r08 grows: a wall nobody had, in its odometry frame, near its start (a robot cannot
            # add walls 200 m from its map within a second: the quarantine keeps such maps aside)
            import dataclasses

            from mapping.wireframe import Wireframe

            r8 = msgs[-1]
            extra = Wireframe.from_polylines([[(0.5, 0.5), (0.5, 3.5)]])
            wf = _union(r8.wireframe, extra)
            m2 = dataclasses.replace(r8, seq=2, stamp_ns=time.time_ns(), wireframe=wf)
            since = watcher.count()
            t0 = time.monotonic()
            s.put(keys.robot_map("r08"), encode_message(m2))
            _, t1 = watcher.wait_for_timed(
                lambda m: m.wireframe.n_edges > full.wireframe.n_edges, 10.0, "r08's new wall", since
            )
            print(f"takeover: r08's map in the fused map {1000 * (t1 - t0):.0f} ms after its publish")
            # g1 restarted: the takeover retires, the root follows the new g1 (newer boot)
            boot_before = watcher.wait_for(lambda m: True, 1.0, "any").meta["group_versions"]["g1"][0]
            fleet.start("g1", g1)  # resumes from its store
            wait_until(lambda: "takeover retired" in fleet.log("g0"), 30.0, "the takeover retiring")
            # the robots' heartbeats (each re-sends its latest map every 2 s): the restarted g1
            # may subscribe after a beat (on a loaded machine it did), the next one reaches it
            def back_again(m):
                return (m.meta["group_versions"].get("g1", [0])[0] > boot_before and len(m.robots) == 8
                        and m.wireframe.n_edges > full.wireframe.n_edges)

            deadline = time.monotonic() + 30.0
            for beat in itertools.count(3):
                for m in msgs[4:7]:
                    s.put(keys.robot_map(m.sender), encode_message(m))
                s.put(keys.robot_map("r08"),
                      encode_message(dataclasses.replace(m2, seq=beat, stamp_ns=time.time_ns())))
                try:
                    back = watcher.wait_for(back_again, 2.0, "the new g1 with every map")
                    break
                except TimeoutError:
                    if time.monotonic() > deadline:
                        raise
            assert back.meta["fusers_down"] == []
        finally:
            watcher.close()
            for t in tokens:
                t.undeclare()


def _union(a, b):
    from mapping.wireframe import Wireframe

    n = a.n_vertices
    return Wireframe(
        np.vstack([a.points, b.points]), np.concatenate([a.labels, b.labels]),
        np.vstack([a.edges, b.edges + n]), np.concatenate([a.likelihood, b.likelihood]),
        np.zeros(a.n_edges + b.n_edges, dtype=np.uint64),
    )


@pytest.mark.fleet
def test_late_joiners_land_in_one_group_and_a_standby_root_takes_over(tmp_path, record_property):
    """``wiremap run --fusers 2``'s id ranges: a robot that joins later (``r04b``, ``r09``)
    lands in exactly one group. Two roots: the younger is a standby that publishes nothing;
    kill -9 of the active root: the standby takes over, a subscriber joining after the kill is
    answered at once with the last fused map (every robot), and the tree keeps fusing (a robot
    joining after the failover reaches the map) with versions that never go back."""
    import dataclasses

    from tests.fleet_util import query_fused, record

    views = robot_views("museum", 10, seed=5)
    late = [dataclasses.replace(views[8], sender="r04b", frame="odom/r04b"),
            dataclasses.replace(views[9], sender="r09", frame="odom/r09")]
    msgs = views[:8]
    keys = FleetKeys("tree3")
    ranges = fold_ranges([m.sender for m in msgs], 2)
    assert ranges == ["range::r05", "range:r05:"]
    with in_process_router() as ep, Fleet(tmp_path) as fleet, client(ep) as s:
        bus = ["--connect", ep, "--fleet", "tree3", "--threshold", repr(THR), "--no-refine"]
        for g, pattern in enumerate(ranges):
            fleet.start(f"g{g}", ["fuse", "--group", f"g{g}", "--robots", pattern, *bus])
        fleet.start("rootA", ["fuse", "--of-groups", "*", "--store", str(tmp_path / "sa"), *bus])
        for name in ("g0", "g1", "rootA"):
            fleet.wait_log(name, "ready", 60.0)
        fleet.start("rootB", ["fuse", "--of-groups", "*", "--store", str(tmp_path / "sb"), *bus])
        fleet.wait_log("rootB", "standby root", 60.0)
        tokens = [s.liveliness().declare_token(keys.alive(m.sender)) for m in [*msgs, *late]]
        watcher = FusedWatcher(s, keys)
        try:
            for m in msgs:
                s.put(keys.robot_map(m.sender), encode_message(m))
            watcher.wait_for(lambda m: len(m.robots) == 8, 60.0, "8 robots")
            s.put(keys.robot_map("r04b"), encode_message(late[0]))
            nine = watcher.wait_for(lambda m: "r04b" in m.robots, 20.0, "the late joiner r04b")
            assert len(nine.robots) == 9
            stats = wait_until(
                lambda: (d := query_stats(s, keys, 2.0)) and d["version"] >= nine.seq and d, 10.0,
                "root stats")
            homes = [g for g, d in stats["groups"].items() if "r04b" in d["robots"]]
            assert homes == ["g0"], stats["groups"]
            assert stats["active"] and stats["uncovered"] == []
            # only the active root publishes: every fused map so far came from rootA
            assert "takes over" not in fleet.log("rootB")
            last_a = watcher.wait_for(lambda m: True, 1.0, "any").seq
            t_kill = fleet.kill9("rootA")
            fleet.wait_log("rootB", "takes over", 10.0)
            with client(ep) as joiner:  # a subscriber that comes after the kill
                got = wait_until(lambda: query_fused(joiner, keys, 2.0), 10.0, "an answer from rootB")
            t_answer = time.monotonic()
            assert set(got.robots) == set(nine.robots) and got.seq >= last_a
            assert got.wireframe.n_edges == nine.wireframe.n_edges
            record(record_property, "root_failover_answer_s", round(t_answer - t_kill, 2))
            since = watcher.count()
            s.put(keys.robot_map("r09"), encode_message(late[1]))
            ten = watcher.wait_for(lambda m: "r09" in m.robots, 20.0, "r09 through rootB", since)
            assert len(ten.robots) == 10 and ten.seq > last_a
            seqs = [m.seq for m in watcher.msgs]
            assert seqs == sorted(seqs), seqs  # versions never go back across the failover
            stats = wait_until(
                lambda: (d := query_stats(s, keys, 2.0)) and d["version"] >= ten.seq and d, 10.0,
                "rootB stats")
            assert stats["takeovers"] == 1 and [g for g, d in stats["groups"].items()
                                                 if "r09" in d["robots"]] == ["g1"]
        finally:
            watcher.close()
            for t in tokens:
                t.undeclare()


def test_a_root_resumes_from_its_store(tmp_path):
    """A root's ``--store``: the stored fused map is served at once and its version continues;
    an unreadable one is one line (UserError), or moved aside with ``--reset`` (the version then
    restarts from the wall clock, so it never goes back)."""
    from agents.fleet.fusion.root import RootService

    raws = {m.sender: encode_message(m) for m in robot_views("museum", 4, seed=2)}
    root, msg = _tree(raws, fold_groups(list(raws), 2))
    data = encode_message(root.fused_message(7))
    store = tmp_path / "store"
    store.mkdir()
    (store / "fused.wfm").write_bytes(data)
    svc = RootService(None, FleetKeys("x"), None, THR, store=str(store))
    assert svc.current == data and svc.state.version == msg.seq
    assert svc.state.fused_robots == msg.robots
    (store / "fused.wfm").write_bytes(data[:-1] + bytes([data[-1] ^ 1]))
    with pytest.raises(UserError, match="unreadable"):
        RootService(None, FleetKeys("x"), None, THR, store=str(store))
    t0 = time.time_ns() // 1_000_000
    svc = RootService(None, FleetKeys("x"), None, THR, store=str(store), reset=True)
    assert svc.current is None and svc.state.version >= t0
    assert not (store / "fused.wfm").exists() and list(store.glob("damaged-*/fused.wfm"))


@pytest.mark.fleet
def test_run_with_two_fusers_records_every_robot_and_the_fused_map(tmp_path):
    """``wiremap run --fusers 2``: the report covers every robot, and ``recording.rrd`` (the
    fusers' parts merged) has every robot's map, both partials, the truth and the root's fused map;
    the parts are gone."""
    import json

    from agents.files.rerun_log import read_recording
    from tests.fleet_util import free_port, tcp_endpoint

    out = tmp_path / "out"
    with Fleet(tmp_path) as fleet:
        p = fleet.start("run", ["run", "--world", "paper-small", "--robots", "3", "--fusers", "2",
                                "--duration", "5", "--particles", "3", "--no-progress", "--out", out,
                                "--listen", tcp_endpoint(free_port())])
        assert p.wait(timeout=120) == 0, fleet.log("run")
    assert "Traceback" not in fleet.log("run")
    rep = json.loads((out / "report.json").read_text())
    assert set(rep["per_robot"]) == {"r1", "r2", "r3"}
    assert all(r["vertices"] > 0 for r in rep["per_robot"].values()), rep["per_robot"]
    assert decode_message((out / "fused.wfm").read_bytes()).robots == ("r1", "r2", "r3")
    entities, _ = read_recording(out / "recording.rrd")
    for rid in ("r1", "r2", "r3"):
        assert f"/robots/{rid}/map" in entities, sorted(entities)
    for e in ("/fused/walls", "/groups/g0/walls", "/groups/g1/walls", "/world/truth"):
        assert any(x == e or x.startswith(e + "/") for x in entities), (e, sorted(entities))
    assert not list(out.glob("store*/*.rrd"))


def _partial(group: str, ids: list[str], seq: int) -> object:
    """A partial of ``ids``: one wall per robot, robot ``j``'s wall with bit ``j`` only, the last
    wall with every robot's bit (group ``gK``'s walls 10 K metres to the right of ``g0``'s)."""
    import dataclasses

    from mapping.wireframe import Wireframe

    x0 = 10.0 * int(group[1:])
    wf = Wireframe.from_polylines([[(x0, float(k)), (x0 + 3.0, float(k))] for k in range(len(ids))],
                                  closed=False)
    masks = [1 << k for k in range(len(ids))]
    masks[-1] = (1 << len(ids)) - 1
    wf = Wireframe(wf.points, wf.labels, wf.edges, wf.likelihood, masks)
    m = robot_views("museum", 1)[0]
    return dataclasses.replace(m, kind=m.kind.__class__.FUSED_MAP, sender=group, seq=seq,
                               robots=tuple(ids), wireframe=wf, frame="fleet",
                               meta={"boot": 1, "group": group})


@pytest.mark.fleet
def test_a_root_with_a_min_interval_fuses_what_came_meanwhile_once(tmp_path):
    """``wiremap fuse --of-groups ... --min-interval 2``: the first partial is fused at once;
    three more that come within the interval (g0 twice, g1 once) wait and are fused together,
    once, no sooner than the interval after the first fuse: no fused map carries g0's middle
    partial, and the heartbeats sent meanwhile describe the map they carry (not the partials
    still waiting). A partial still waiting when the root stops is fused into its store."""
    from agents.fleet.fusion.root import read_root_store

    keys = FleetKeys("rooti")
    store = tmp_path / "store"
    with in_process_router() as ep, Fleet(tmp_path) as fleet, client(ep) as s:
        fleet.start("root", ["fuse", "--of-groups", "g0,g1", "--connect", ep, "--fleet", "rooti",
                             "--threshold", repr(THR), "--min-interval", "2", "--heartbeat", "0.3",
                             "--store", str(store)])
        fleet.wait_log("root", "root fuser ready", 60.0)
        watcher = FusedWatcher(s, keys)
        try:
            key = "wiremap/rooti/groups/{}/map"
            s.put(key.format("g0"), encode_message(_partial("g0", ["a1", "a2"], 1)))
            _, t1 = watcher.wait_for_timed(lambda m: m.meta["group_versions"].get("g0") == [1, 1], 30.0,
                                           "g0's first partial")
            since = watcher.count()
            s.put(key.format("g0"), encode_message(_partial("g0", ["a1", "a2"], 2)))
            s.put(key.format("g0"), encode_message(_partial("g0", ["a1", "a2", "a3"], 3)))
            s.put(key.format("g1"), encode_message(_partial("g1", ["b1"], 1)))
            both, t2 = watcher.wait_for_timed(lambda m: "g1" in m.meta["group_versions"], 30.0,
                                              "both groups", since)
            assert both.meta["group_versions"] == {"g0": [1, 3], "g1": [1, 1]}
            assert both.robots == ("a1", "a2", "a3", "b1")
            assert t2 - t1 >= 1.5, t2 - t1
            seen = [(m.robots, m.meta["group_versions"]) for m in watcher.msgs]
            assert all(gv.get("g0") != [1, 2] for _, gv in seen), seen
            # every message (heartbeats included) lists the partials of the map it carries
            assert all(gv == {"g0": [1, 1]} for r, gv in seen if r == ("a1", "a2")), seen
            assert sum(r == ("a1", "a2") for r, _ in seen) >= 3, seen  # heartbeats in the wait
            s.put(key.format("g1"), encode_message(_partial("g1", ["b1", "b2"], 2)))
            time.sleep(0.3)  # taken, waiting for the interval
            assert fleet.stop("root") == 0
        finally:
            watcher.close()
    stored = decode_message(read_root_store(store, False))
    assert stored.robots == ("a1", "a2", "a3", "b1", "b2"), stored.robots


def test_the_root_takes_partials_past_64_robots():
    """Partials of 40 and 60 robots (and then 100 and 5): the fused map has every robot, robot
    ``b59`` owns bit 99, ``b58`` bit 98 (masks past bit 63), and it travels as format version 2;
    the partial of
    100 robots itself travels too."""
    root = RootState(THR)
    a = [f"a{k:02d}" for k in range(40)]
    b = [f"b{k:02d}" for k in range(60)]
    assert root.offer("g0", decode_message(encode_message(_partial("g0", a, 1))))
    assert root.offer("g1", decode_message(encode_message(_partial("g1", b, 1))))
    assert root.fuse() and len(root.fused_robots) == 100 and not root.refused
    data = encode_message(root.fused_message(0))
    assert data[1] == 2
    out = decode_message(data)
    assert out.robots == tuple(a + b)
    masks = {int(v) for v in out.wireframe.sources.tolist()}
    assert {1 << 98, 1 << 40, 1, (1 << 100) - (1 << 40), (1 << 40) - 1} <= masks, sorted(masks)
    wide = [f"c{k:03d}" for k in range(100)]
    assert root.offer("g0", decode_message(encode_message(_partial("g0", wide, 2))))
    assert root.offer("g1", decode_message(encode_message(_partial("g1", [f"d{k}" for k in range(5)], 2))))
    assert root.fuse() and len(root.fused_robots) == 105
    masks = {int(v) for v in decode_message(encode_message(root.fused_message(0))).wireframe.sources.tolist()}
    assert (1 << 100) - 1 in masks and 1 << 103 in masks and ((1 << 105) - 1) ^ ((1 << 100) - 1) in masks


def test_the_root_refuses_a_partial_past_the_format_bound(monkeypatch):
    """A partial that would bring the fleet past ``wire_codec.MAX_ROBOTS`` (4,096; lowered here
    to 64 to keep the test small) is refused (counted per group) and the group's previous
    partial stays; nothing raises."""
    import wire_codec

    monkeypatch.setattr(wire_codec, "MAX_ROBOTS", 64)
    root = RootState(THR)
    assert root.offer("g0", _partial("g0", [f"a{k:02d}" for k in range(40)], 1))
    assert root.offer("g1", _partial("g1", [f"b{k:02d}" for k in range(24)], 1))
    assert root.fuse() and len(root.fused_robots) == 64
    assert not root.offer("g1", _partial("g1", [f"b{k:02d}" for k in range(25)], 2))
    assert root.refused == {"g1": 1} and root.partials["g1"].key == (1, 1)
    assert not root.fuse() and len(root.fused_robots) == 64
    decode_message(encode_message(root.fused_message(0)))  # still a valid message


def test_one_process_and_tree_past_64_robots():
    """70 robots: one FusionState takes the 65th robot and on (robot k owns bit k, up to 69) and
    a tree of the fold's subtrees (64 + 6: the second partial's bits land at 64..69 at the
    root) gives the same walls, robots and sources; the fused map is format version 2."""
    from mapping.wireframe import mask_or

    raws = {m.sender: encode_message(m) for m in robot_views("museum", 70, seed=4, radius=10)}
    st, ref = _one_process(raws, refine=False)
    assert st.stats.rejected == 0 and len(ref.robots) == 70
    assert encode_message(st.fused_message(0))[1] == 2
    assert mask_or(ref.wireframe.sources) == (1 << 70) - 1  # every robot, bits 64..69 included
    groups = fold_groups(list(raws), 2)
    assert [len(g) for g in groups] == [64, 6]
    root, out = _tree(raws, groups, refine=False)
    assert root.exact and not root.refused
    _same_map(ref, out)


def test_the_fusion_state_refuses_a_robot_past_the_bound(monkeypatch):
    """One more robot than ``MAX_ROBOTS`` (4,096; lowered to 66 here) is counted and dropped
    (``rejected_by.too_many_robots``); the 65th and 66th are taken."""
    import agents.fleet.fusion.state as state_mod

    monkeypatch.setattr(state_mod, "MAX_ROBOTS", 66)
    msgs = robot_views("museum", 67, seed=5, radius=8)
    st = FusionState(FusionConfig(threshold=THR, refine=False))
    took = [st.offer(encode_message(m), m.sender) for m in msgs]
    assert took == [True] * 66 + [False]
    assert st.stats.rejected_by == {"too_many_robots": 1}
    st.fuse(full=True)
    assert len(decode_message(encode_message(st.fused_message(0))).robots) == 66
