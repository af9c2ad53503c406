"""Incremental update: new aligned trips update the existing map instead of rebuilding it.

Every existing instance takes part in association as one pseudo-member (its fused geometry,
sigma = its uncertainty) next to the new trips' instances. Only groups that contain a new
instance are refitted; instances no new trip touched keep their geometry and properties.

Lines are refitted recursively: the map's instance stands for all its members (its line, with
the weight of its standard error, ``uncertainty_m``: about sigma / sqrt(trips)) and is fused
with the new members only, so the cost of adding a trip does not grow with the trips already
in the map. This is the recursive form of the weighted least-squares profile of ``fusion``: a
new trip moves the line by its weight share, and the robust fit rejects it where it is off
the map's line. The statistics validation reads (support, scatter, rejected share, outlier
trips, times) are carried over from the map's instance and updated with the new members.
Polygons (few, small groups) are refitted from their stored members
(``TopologyResult.members``). Ids continue (``identity``). Lane graph and validation are then
recomputed over the map (cheap next to fusion).

A trip already in the map (re-aligned after a correction) cannot be added again: rebuild with
``generate_topology(..., previous=old)``, which keeps the ids.
"""

from __future__ import annotations

import time
from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np

from csr_core.errors import ReconstructionError
from csr_core.topology.association import MAP_MEMBER_KEY, Member, associate_lines, associate_polygons
from csr_core.topology.derived_centerlines import is_derived
from csr_core.topology.fusion import FusedInstance
from csr_core.topology.identity import assign_ids
from csr_core.topology.instances import (
    TopologyResult,
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

MIN_ANCHOR_SIGMA_M = 0.02  # a map instance never weighs more than one of 2 cm standard error


def update_topology(
    previous: TopologyResult,
    new_instances_per_trip: Mapping[str, Sequence[TripInstance]],
    new_noise_per_trip: Mapping[str, Mapping[ElementType, ElementNoise]],
    params: TopologyParams = DEFAULT,
    trip_times: Mapping[str, object] | None = None,
    match_pairs: Sequence = (),
    paths_xy_per_trip: Mapping[str, np.ndarray] | None = None,
) -> TopologyResult:
    """``previous`` map plus new trips (keys not in it) -> updated map; see the module docstring."""
    t0 = time.perf_counter()
    known = {m.trip_key for mem in previous.members.values() for m in mem} | set(previous.trip_points)
    again = sorted(set(new_instances_per_trip) & known)
    if again:
        raise ReconstructionError(f"trips already in the map (rebuild instead): {again[:3]}")
    new_by_type, rejected = make_members(new_instances_per_trip, new_noise_per_trip, params)
    old_by_type: dict[ElementType, list[MapFeature]] = {t: [] for t in ElementType}
    for f in (*previous.features, *previous.suppressed):
        if not is_derived(f):  # derived again below from the updated dividers and boundaries
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
        pseudo = [_anchor(k, f) for k, f in enumerate(old)]
        pool = pseudo + new
        groups = (
            associate_polygons(pool, params) if etype.is_polygon else associate_lines(pool, etype, params)
        )
        # 2. refit the touched groups: lines from the map's instance (standing for its members)
        #    plus the new ones; polygons from their stored members plus the new ones
        touched_members: list[Member] = []
        touched: set[int] = set()
        for g in groups:
            if all(k < len(pseudo) for k in g):
                continue
            for k in g:
                if k < len(pseudo):
                    touched.add(k)
                    touched_members.extend(
                        previous.members.get(old[k].feature_id, ()) if etype.is_polygon else (pool[k],)
                    )
                else:
                    touched_members.append(pool[k])
        kept.extend(f for k, f in enumerate(old) if k not in touched)
        touched_old.extend(old[k] for k in sorted(touched))
        for fused, mem in fuse_type(touched_members, etype, params):
            anchors = [old[m.index] for m in mem if m.trip_key == MAP_MEMBER_KEY]
            if anchors:
                real = tuple(m for m in mem if m.trip_key != MAP_MEMBER_KEY)
                refit.append(_continued_feature(fused, mem, anchors, times))
                refit_members.append(
                    tuple(m for a in anchors for m in previous.members.get(a.feature_id, ())) + real
                )
            else:
                refit.append(feature_from_fused(fused, mem, times or None))
                refit_members.append(mem)
    t1 = time.perf_counter()
    # 3. directions, then ids: refitted instances continue the touched ones
    trip_paths = {**previous.trip_paths, **path_probes(paths_xy_per_trip)}
    refit = orient_centerlines(refit, trip_paths, params)
    refit = assign_ids(refit, touched_old, params)
    taken = {f.feature_id for f in kept}
    for i, f in enumerate(refit):
        if f.feature_id in taken:  # a new id colliding with an untouched instance
            refit[i] = type(f)(f.type, f.points_xy_world, f.style, f"{f.feature_id}-u", f.properties)
    members = {f.feature_id: previous.members[f.feature_id] for f in kept if f.feature_id in previous.members}
    members.update({f.feature_id: m for f, m in zip(refit, refit_members, strict=True)})
    trip_points = {**previous.trip_points, **trip_probe_points(new_instances_per_trip)}
    features = [_strip(f) for f in kept] + refit
    return finish(
        features,
        members,
        trip_points,
        params,
        match_pairs,
        {"fuse": t1 - t0, "refit_features": float(len(refit))},
        times,
        (*previous.rejected_members, *rejected),
        trip_paths,
        (*previous.features, *previous.suppressed),
    )


def _strip(f: MapFeature) -> MapFeature:
    """An untouched instance: its validation fields are recomputed."""
    props = {k: v for k, v in f.properties.items() if k not in ("flags", "coverage_trips", "passed_trips")}
    return MapFeature(f.type, f.points_xy_world, f.style, f.feature_id, props)


def _anchor(k: int, f: MapFeature) -> Member:
    """The map's instance ``k`` as a pseudo-member: its line, weighing as its standard error."""
    sigma = max(float(f.properties.get("uncertainty_m", 0.05)), MIN_ANCHOR_SIGMA_M)
    n_obs = int(f.properties.get("support_observations", 1))
    return Member(MAP_MEMBER_KEY, k, TripInstance(f.type, f.points_xy_world, f.style, n_obs), sigma)


def _continued_feature(
    fused: FusedInstance,
    members: Sequence[Member],
    anchors: Sequence[MapFeature],
    trip_times: Mapping[str, object],
) -> MapFeature:
    """The properties of a map instance refitted with new members (``feature_from_fused`` for
    the anchors' members and the new ones together): supports add up, the scatter and the
    rejected share are the trip-weighted means of the map's and the new members', times
    span both."""
    real = [(k, m) for k, m in enumerate(members) if m.trip_key != MAP_MEMBER_KEY]
    old_trips = {t for a in anchors for t in a.properties.get("trips", ())}
    trips = sorted(old_trips | {m.trip_key for _, m in real})
    outliers = {
        members[k].trip_key
        for k in fused.outlier_members
        if k < len(members) and members[k].trip_key != MAP_MEMBER_KEY
    }
    z2_old = sum(
        float(a.properties.get("scatter_ratio", 1.0)) ** 2 * int(a.properties.get("support_trips", 1))
        for a in anchors
    )
    n_z_old = sum(int(a.properties.get("support_trips", 1)) for a in anchors)
    z2_new = [
        fused.member_scatter2[k]
        for k, _ in real
        if k < len(fused.member_scatter2)
        and np.isfinite(fused.member_scatter2[k])
        and members[k].trip_key not in outliers
    ]
    scatter = float(np.sqrt((z2_old + sum(z2_new)) / max(n_z_old + len(z2_new), 1)))
    rejected_old = sum(
        float(a.properties.get("rejected_weight_share", 0.0)) * int(a.properties.get("support_trips", 1))
        for a in anchors
    )
    rejected = (rejected_old + len(outliers)) / max(n_z_old + len(real), 1)
    new_times = [trip_times.get(m.trip_key) for _, m in real]
    seen: list[Any] = [
        t for t in [a.properties.get("first_seen") for a in anchors] + new_times if t is not None
    ]
    confirmed: list[Any] = [
        t for t in [a.properties.get("last_confirmed") for a in anchors] + new_times if t is not None
    ]
    first = min(
        anchors, key=lambda a: (a.properties.get("first_seen") is None, str(a.properties.get("first_seen")))
    )
    props = {
        "support_trips": len(trips),
        "support_observations": int(
            sum(int(a.properties.get("support_observations", 0)) for a in anchors)
            + sum(m.instance.n_observations for _, m in real)
        ),
        "uncertainty_m": round(float(fused.uncertainty_m), 4),
        "first_seen": min(seen) if seen else None,
        "last_confirmed": max(confirmed) if confirmed else None,
        "style": fused.style.value if fused.style is not None else None,
        "trips": trips,
        "scatter_ratio": round(scatter, 3),
        "rejected_weight_share": round(float(rejected), 3),
        "outlier_trips": sorted(
            {t for a in anchors for t in a.properties.get("outlier_trips", ())} | outliers
        ),
        "max_internal_gap_m": round(float(fused.max_internal_gap_m), 2),
        "first_trip": first.properties.get("first_trip", trips[0] if trips else ""),
    }
    return MapFeature(
        type=fused.type,
        points_xy_world=fused.points_xy_world,
        style=fused.style,
        feature_id="",
        properties=props,
    )
