"""Incremental update: new aligned trips update the existing map instead of rebuilding it.

Every existing instance takes part in association as one pseudo-member (its fused geometry,
sigma = its uncertainty) next to the new trips' instances. Only groups that contain a new
instance are refitted, from the stored members of the existing instances in the group plus
the new ones (``TopologyResult.members``); their ids continue (``identity``). Instances no new
trip touched keep their geometry and properties unchanged. Lane graph and validation are then
recomputed over the map (cheap next to fusion).

A trip already in the map (re-aligned after a correction) cannot be added again: rebuild with
``generate_topology(..., previous=old)``, which keeps the ids.
"""

from __future__ import annotations

import time
from collections.abc import Mapping, Sequence

import numpy as np

from csr_core.errors import ReconstructionError
from csr_core.topology.association import Member, associate_lines, associate_polygons
from csr_core.topology.instances import (
    TopologyResult,
    assign_ids,
    feature_from_fused,
    finish,
    fuse_type,
    make_members,
    orient_centerlines,
    path_probes,
    trip_probe_points,
)
from csr_core.topology.params import DEFAULT, TopologyParams
from csr_core.types import ElementNoise, ElementType, MapFeature, TripInstance

MAP_KEY = "<map>"


def update_topology(previous: TopologyResult, new_instances_per_trip: Mapping[str, Sequence[TripInstance]],
                    new_noise_per_trip: Mapping[str, Mapping[ElementType, ElementNoise]],
                    params: TopologyParams = DEFAULT, trip_times: Mapping[str, object] | None = None,
                    match_pairs: Sequence = (),
                    paths_xy_per_trip: Mapping[str, np.ndarray] | None = None) -> TopologyResult:
    """``previous`` map plus new trips (keys not in it) -> updated map; see the module docstring."""
    t0 = time.perf_counter()
    known = {m.trip_key for mem in previous.members.values() for m in mem} | set(previous.trip_points)
    again = sorted(set(new_instances_per_trip) & known)
    if again:
        raise ReconstructionError(f"trips already in the map (rebuild instead): {again[:3]}")
    new_by_type, rejected = make_members(new_instances_per_trip, new_noise_per_trip, params)
    old_by_type: dict[ElementType, list[MapFeature]] = {t: [] for t in ElementType}
    for f in (*previous.features, *previous.suppressed):
        old_by_type[f.type].append(f)
    kept: list[MapFeature] = []
    refit: list[MapFeature] = []
    refit_members: list[tuple[Member, ...]] = []
    touched_old: list[MapFeature] = []
    times = {**previous.trip_times, **(trip_times or {})}
    for etype in ElementType:
        old, new = old_by_type[etype], new_by_type[etype]
        if not new:
            kept.extend(old)
            continue
        # 1. associate the map's instances (as pseudo-members) with the new trips' instances
        pseudo = [Member(MAP_KEY, k, TripInstance(etype, f.points_xy_world, f.style), max(
            float(f.properties.get("uncertainty_m", 0.05)), 0.02)) for k, f in enumerate(old)]
        pool = pseudo + new
        groups = (associate_polygons(pool, params) if etype.is_polygon
                  else associate_lines(pool, etype, params))
        # 2. refit the touched groups from their stored members plus the new ones
        touched_members: list[Member] = []
        touched: set[int] = set()
        for g in groups:
            if all(k < len(pseudo) for k in g):
                continue
            for k in g:
                if k < len(pseudo):
                    touched.add(k)
                    touched_members.extend(previous.members.get(old[k].feature_id, ()))
                else:
                    touched_members.append(pool[k])
        kept.extend(f for k, f in enumerate(old) if k not in touched)
        touched_old.extend(old[k] for k in sorted(touched))
        for fused, mem in fuse_type(touched_members, etype, params):
            refit.append(feature_from_fused(fused, mem, times or None))
            refit_members.append(mem)
    t1 = time.perf_counter()
    # 3. directions, then ids: refitted instances continue the touched ones
    refit = orient_centerlines(refit, path_probes(paths_xy_per_trip), params)
    refit = assign_ids(refit, touched_old, params)
    taken = {f.feature_id for f in kept}
    for i, f in enumerate(refit):
        if f.feature_id in taken:  # a new id colliding with an untouched instance
            refit[i] = type(f)(f.type, f.points_xy_world, f.style, f"{f.feature_id}-u", f.properties)
    members = {f.feature_id: previous.members[f.feature_id] for f in kept if f.feature_id in previous.members}
    members.update({f.feature_id: m for f, m in zip(refit, refit_members, strict=True)})
    trip_points = {**previous.trip_points, **trip_probe_points(new_instances_per_trip)}
    features = [_strip(f) for f in kept] + refit
    return finish(features, members, trip_points, params, match_pairs,
                  {"fuse": t1 - t0, "refit_features": float(len(refit))}, times,
                  (*previous.rejected_members, *rejected))


def _strip(f: MapFeature) -> MapFeature:
    """An untouched instance: its validation fields are recomputed."""
    props = {k: v for k, v in f.properties.items() if k not in ("flags", "coverage_trips")}
    return MapFeature(f.type, f.points_xy_world, f.style, f.feature_id, props)
