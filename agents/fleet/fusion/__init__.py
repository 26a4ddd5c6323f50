"""The fusion service: every robot's latest map -> one fleet map.

Modules, from the bytes in to the map out:

* :mod:`~agents.fleet.fusion.codec`: map messages <-> bytes, the order of a robot's maps;
* :mod:`~agents.fleet.fusion.intake`: what is accepted from the bus (:class:`InputLimits`), the
  bounded inbox (:class:`Intake`), the drop log;
* :mod:`~agents.fleet.fusion.state`: :class:`FusionState`, the pure core (no zenoh, no rerun,
  no clock of its own): keeps each robot's latest :class:`~wire_codec.message.MapMessage`,
  recomputes the fused map, stores and restores itself on disk;
* :mod:`~agents.fleet.fusion.store`: the store's files and the background writer;
* :mod:`~agents.fleet.fusion.stats`: counters and publish latencies;
* :mod:`~agents.fleet.fusion.service`: :func:`serve`, the Zenoh shell: subscribes to
  ``robots/*/map`` (through :class:`Intake`, a bounded FIFO), ``robots/*/pose`` and
  ``robots/*/viz`` (only the latest per robot matters; only when it writes a Rerun recording,
  their only use) and ``alive/*``; publishes the fused map on every change and answers queries
  for it and for its counters (``fused/stats``); logs to Rerun.

Order independence: a robot's latest map is the one with the greatest ``(meta["boot"], seq,
sha256 of its bytes)``, whatever the order of arrival, and duplicates are no-ops. Robot ``k`` of
the sorted ids owns bit ``k`` of ``Wireframe.sources`` (``MapMessage.robots`` lists them): at
most ``wire_codec.MAX_ROBOTS`` (4,096) robots; past 64 the masks are Python ints
(:func:`mapping.wireframe.as_masks`) and the fused map travels as format version 2.

Fleet frame and merge, per robot in sorted-id order (choices where the paper and the issue are
silent):

1. the map (in the robot's odometry frame) is moved by its start pose (``MapMessage.origin``);
2. if ``FusionConfig.refine`` is on, a wireframe ICP (:func:`mapping.fleet.align_maps`) aligns
   it to the fused map of the robots before it (the first robot is the anchor). The correction
   is kept only when it is small (``max_refine_m`` / ``max_refine_rad``): the start poses are
   known, ICP only removes residual odometry drift;
3. :func:`mapping.merge.merge` folds the robots' maps together (a fixed binary tree over the
   sorted ids, see :meth:`FusionState.compute`) with the merge threshold
   ``FusionConfig.threshold`` (default 0.2 m, raised to the largest ``resolution`` among the
   robot maps if one is coarser). The fused map travels quantised at the finest robot
   resolution, with the threshold in its ``meta``.

Finally :func:`mapping.fleet.close_frontiers` removes frontiers of one robot that another robot's walls
close (see there).

Two paths (:meth:`FusionState.compute`), because step 2 is the expensive one (an ICP is 4-7 ms
of CPU on paper-small, a merge ~1 ms):

* the **full path** runs step 2 for every robot whose alignment is not current and is a
  deterministic function of the set of latest maps (property tests over permutations and
  duplicates). It runs when the service has had no new map for ``full_after_s`` (0.5 s) and
  before the final store write at exit;
* the **fast path**, on every batch of arrivals, reuses each robot's cached alignment and
  re-merges only the tree's nodes above the robots whose map or correction changed (the
  nodes are cached by the identity of their inputs). It equals the full path's map once
  the alignments are current (:attr:`FusionState.converged`). The service runs no ICP inside
  a fast fuse: after publishing it re-aligns one robot the fuse found wanting it
  (:meth:`FusionState.realign`: its map grew or shrank by ``max(realign_vertices,
  realign_fraction * n)`` vertices, its start pose or boot changed, or its stale alignment is
  ``realign_s`` old), and the next fuse applies the new correction.

The service drains the whole inbox, decodes each robot's newest map of it, fuses once and
publishes once per loop iteration, so a burst of maps costs one fold. The store is written by a
background thread (:class:`~agents.fleet.fusion.store.StoreWriter`); publish latencies go to an
append-only ``latency.log``.

Hostile or broken input (choices; the counters are in :class:`FusionStats`, served on
``wiremap/<fleet>/fused/stats`` and written to the store's ``state.json``):

* in Zenoh's thread, before anything is decoded (:class:`Intake`): a payload over
  ``InputLimits.max_bytes`` is dropped (``oversized``); each key has a token bucket
  (``rate_hz``, ``burst``; ``rate_limited``); each key's queue holds at most ``queue_depth``
  payloads (the oldest goes: maps are whole states) and all queues together at most
  ``queue_bytes`` (``overflow``); at most ``max_keys`` keys are tracked. Memory is bounded by
  ``queue_bytes`` plus one payload per side channel and robot, whatever arrives;
* in the main thread, of each key's payloads drained together only the newest is decoded; the
  older ones are read up to their header (``superseded``, or counted below when the header
  fails; :meth:`FusionState.offer_latest`, which says why that lets no bad map through); a
  map whose body is byte for byte its robot's latest accepted body is not read again, its
  wireframe is the latest one's, and every check below runs on it (``same_body``;
  :mod:`agents.fleet.fusion.facts` says why each gives the full path's answer);
* in the main thread (:meth:`FusionState.offer`): the codec with the fusion's tighter
  :class:`~wire_codec.Limits` (``malformed``, by error class); a key whose id chunk is not a
  valid name, a fused map on a robot key, an envelope sender that differs from the key, a
  robot past the 4,096th (``rejected``, by reason); a decodable map with absurd content -- coordinates beyond
  ``max_extent_m`` in the fleet frame, a resolution over ``max_resolution_m``, a non-finite or
  negative ``meta.t``, a ``meta.boot`` that is not an integer or lies in the future
  (``absurd``, by reason).

Every drop is counted; :class:`~agents.fleet.fusion.intake.DropLog` prints at most one line per ``period``
summarising them.
The fused map is only ever recomputed from accepted maps, so the last good map keeps being
served.
"""

from agents.fleet.fusion.codec import decode_message, encode_message, order_key
from agents.fleet.fusion.intake import DropLog, InputLimits, Intake, implausible, over_budget
from agents.fleet.fusion.service import FusionService, ServeOptions, serve
from agents.fleet.fusion.state import (
    DEFAULT_RESOLUTION,
    DEFAULT_THRESHOLD,
    FUSION_ID,
    Alignment,
    FusionConfig,
    FusionState,
    RobotEntry,
    default_merge,
    merge_threshold_of,
)
from agents.fleet.fusion.stats import MAX_LATENCIES, FusionStats, LatencyWindow, latency_summary
from agents.fleet.fusion.store import (
    LATENCY_LOG,
    SNAPSHOT,
    StoreContents,
    StoreDamaged,
    StoreJob,
    StoreWriter,
    append_latency_log,
    read_latency_log,
    read_store,
)

__all__ = [
    "DEFAULT_RESOLUTION",
    "DEFAULT_THRESHOLD",
    "FUSION_ID",
    "LATENCY_LOG",
    "MAX_LATENCIES",
    "SNAPSHOT",
    "Alignment",
    "DropLog",
    "FusionConfig",
    "FusionService",
    "FusionState",
    "FusionStats",
    "InputLimits",
    "Intake",
    "LatencyWindow",
    "RobotEntry",
    "ServeOptions",
    "StoreContents",
    "StoreDamaged",
    "StoreJob",
    "StoreWriter",
    "append_latency_log",
    "decode_message",
    "default_merge",
    "encode_message",
    "implausible",
    "latency_summary",
    "merge_threshold_of",
    "order_key",
    "over_budget",
    "read_latency_log",
    "read_store",
    "serve",
]
