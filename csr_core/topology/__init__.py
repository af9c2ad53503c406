"""Lane instance topology generation and automatic validation (paper section III-E).

    generate_topology(instances_per_trip, noise_per_trip) -> TopologyResult
    update_topology(previous, new_instances_per_trip, new_noise_per_trip) -> TopologyResult

The recipe, one module per step: per element type, associate the aligned instances of all
trips (``association``), fuse each group robustly (``fusion``), give every instance a stable id
(``identity``), derive centrelines where none was perceived (``derived_centerlines``), link the
lanes (``lane_graph``) and validate instances and tiles
(``validation``). ``update_topology`` (``incremental``) refits only what new trips touch.

Input: each trip's ``TripInstance``s already in the world frame of the aligned poses, and each
trip's per-type ``ElementNoise`` from single-trip reconstruction (they set the weights and the
association gates). Output features carry in ``properties``: ``support_trips``,
``support_observations``, ``uncertainty_m``, ``first_seen``, ``last_confirmed`` (from
``trip_times``, any comparable value such as ISO time strings), ``style``, ``trips`` and the
validation ``flags``.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Mapping, Sequence

import numpy as np

from csr_core.topology.association import Member
from csr_core.topology.identity import assign_ids
from csr_core.topology.incremental import update_topology
from csr_core.topology.instances import (
    TopologyResult,
    feature_from_fused,
    finish,
    fuse_type,
    make_members,
    orient_centerlines,
    path_probes,
    reposition_instances,
    trip_probe_points,
)
from csr_core.topology.lane_graph import LaneGraph
from csr_core.topology.params import DEFAULT, TopologyParams
from csr_core.topology.validation import SUSPECT, TileQuality, ValidationFlag
from csr_core.types import ElementNoise, ElementType, MapFeature, TripInstance

log = logging.getLogger(__name__)

__all__ = [
    "DEFAULT",
    "SUSPECT",
    "LaneGraph",
    "TileQuality",
    "TopologyParams",
    "TopologyResult",
    "ValidationFlag",
    "generate_topology",
    "reposition_instances",
    "update_topology",
]


def generate_topology(
    instances_per_trip: Mapping[str, Sequence[TripInstance]],
    noise_per_trip: Mapping[str, Mapping[ElementType, ElementNoise]],
    params: TopologyParams = DEFAULT,
    previous: TopologyResult | None = None,
    trip_times: Mapping[str, object] | None = None,
    match_pairs: Sequence = (),
    paths_xy_per_trip: Mapping[str, np.ndarray] | None = None,
) -> TopologyResult:
    """Fuse the aligned instances of all trips into the map (paper III-E) and validate it.

    ``instances_per_trip``: trip key -> its instances in the world frame (after alignment);
    ``noise_per_trip``: trip key -> per-type noise from single-trip reconstruction;
    ``previous``: an earlier map whose ids continue (rebuild with more or re-aligned trips);
    ``trip_times``: trip key -> time (first_seen / last_confirmed); ``match_pairs``: the
    alignment's match pairs (``MatchPairRecord``) for the residual check;
    ``paths_xy_per_trip``: trip key -> aligned positions ``(N, 2)`` (directions of centrelines;
    the trips that drove alongside a line without seeing it, against ghosts).
    """
    t0 = time.perf_counter()
    # 1. members: every trip instance with its lateral sigma (noise + alignment); zig-zags out
    by_type, rejected = make_members(instances_per_trip, noise_per_trip, params)
    # 2.-3. associate and fuse, per type
    features: list[MapFeature] = []
    member_lists: list[tuple[Member, ...]] = []
    for etype in ElementType:
        for fused, mem in fuse_type(by_type[etype], etype, params):
            features.append(feature_from_fused(fused, mem, trip_times))
            member_lists.append(mem)
    t1 = time.perf_counter()
    # 4. centreline directions from the trips that drove them, stable ids
    paths = path_probes(paths_xy_per_trip)
    features = orient_centerlines(features, paths, params)
    features = assign_ids(
        features, (*previous.features, *previous.suppressed) if previous is not None else (), params
    )
    members = {f.feature_id: m for f, m in zip(features, member_lists, strict=True)}
    t2 = time.perf_counter()
    # 5.-7. ghosts held back, centrelines derived where none was perceived, validation, lane graph
    result = finish(
        features,
        members,
        trip_probe_points(instances_per_trip),
        params,
        match_pairs,
        {"fuse": t1 - t0, "ids": t2 - t1},
        trip_times,
        rejected,
        paths,
        (*previous.features, *previous.suppressed) if previous is not None else (),
    )
    log.info(
        "topology: %d trips, %d features, %d flags in %.2f s",
        len(instances_per_trip),
        len(result.features),
        len(result.flags),
        time.perf_counter() - t0,
    )
    return result
