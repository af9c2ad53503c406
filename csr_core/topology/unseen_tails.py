"""End stretches of a fused line that one trip alone saw and other trips drove past unseen.

A fused line ends where its members' ends say (``fusion.fuse_lines``: the robust ends of the
members). When one member runs on past all the others, the line runs on with it: rightly when
that trip alone drove there (each trip sees a different part of a long line), wrongly when the
others drove past the same stretch and saw nothing there (a dashed divider spliced by one trip
into the dashes of a line crossing a junction, 10 m past where its paint starts: Karlsruhe
standard s1).

The test is the one ``instances.finish`` applies to whole lines (``validation.seen_too_rarely``), applied to the
stretch at each end that at most one trip covers (with any instance of the type, fused into this
line or another: a trip may have seen the stretch in a piece of its own): it is cut when at least
``SUPPRESS_MIN_PASSING`` trips that did not see it drove alongside it and fewer than
``LOW_SUPPORT_SHARE`` of the trips that had it in view saw it.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import replace

import numpy as np
from scipy.spatial import cKDTree

from csr_core.single_trip.splicing import resample_polyline
from csr_core.topology.association import Member
from csr_core.topology.fusion import arclength
from csr_core.topology.params import TopologyParams
from csr_core.topology.validation import passing_counts, seen_too_rarely
from csr_core.types import ElementType, MapFeature

#: a member covers a vertex of the fused line within this many of its sigmas (perception and
#: alignment noise, ``Member.sigma_m``), and never less than ``MIN_COVER_M``
COVER_SIGMAS = 3.0
MIN_COVER_M = 0.5


class TypePoints:
    """Every fused member of one element type, densified, in one KD-tree: which trips saw a place
    (a trip's instance may have gone to another feature: a line one trip saw in two pieces)."""

    def __init__(self, members: Sequence[Member], spacing_m: float) -> None:
        keys: dict[str, int] = {}
        pts, trip, radius = [], [], []
        for m in members:
            p = np.asarray(m.instance.points_xy_world, float)
            dense = resample_polyline(p, spacing_m) if len(p) > 1 else p
            pts.append(dense)
            trip.append(np.full(len(dense), keys.setdefault(m.trip_key, len(keys))))
            radius.append(np.full(len(dense), max(COVER_SIGMAS * m.sigma_m, MIN_COVER_M)))
        self.keys = list(keys)
        self.points = np.concatenate(pts) if pts else np.zeros((0, 2))
        self.trip = np.concatenate(trip) if trip else np.zeros(0, dtype=int)
        self.radius = np.concatenate(radius) if radius else np.zeros(0)
        self.tree = cKDTree(self.points) if len(self.points) else None

    def support(self, line_xy: np.ndarray) -> tuple[np.ndarray, list[list[str]]]:
        """For each vertex of ``line_xy (M, 2)``: how many distinct trips have a member point
        within that member's cover radius (``COVER_SIGMAS`` of its sigma), and which."""
        if self.tree is None:
            return np.zeros(len(line_xy), dtype=int), [[] for _ in line_xy]
        near = self.tree.query_ball_point(line_xy, float(self.radius.max()))
        trips = []
        for j, idx in enumerate(near):
            idx = np.asarray(idx, dtype=int)
            d = np.hypot(*(self.points[idx] - line_xy[j]).T) if len(idx) else np.zeros(0)
            trips.append(sorted(self.keys[t] for t in np.unique(self.trip[idx[d <= self.radius[idx]]])))
        return np.array([len(t) for t in trips], dtype=int), trips


def _end_run(
    points: TypePoints, line_xy: np.ndarray, from_head: bool, chunk: int = 16
) -> tuple[int, list[str]] | None:
    """The vertices at the head (or tail) of ``line_xy`` covered by at most one trip: how many,
    and the trips that cover them; None when no vertex has two. Walked from the end a ``chunk``
    at a time (most lines have two trips within a few metres of their ends)."""
    order = np.arange(len(line_xy)) if from_head else np.arange(len(line_xy))[::-1]
    seen: set[str] = set()
    for start in range(0, len(order), chunk):
        idx = order[start : start + chunk]
        support, trips = points.support(line_xy[idx])
        above = np.flatnonzero(support > 1)
        stop = int(above[0]) if len(above) else len(idx)
        for t in trips[:stop]:
            seen.update(t)
        if len(above):
            return start + stop, sorted(seen)
    return None


def trim_unseen_tails(
    features: Sequence[MapFeature],
    members: Mapping[str, Sequence[Member]],
    trip_paths: Mapping[str, np.ndarray],
    params: TopologyParams,
    min_length_m: float,
) -> tuple[list[MapFeature], int]:
    """``features`` with the end stretches of their lines that one trip alone covered and that
    other trips drove past unseen cut off (module docstring); stretches shorter than
    ``min_length_m`` are left (the ends of members scatter by that much). Returns the features
    and the number of stretches cut."""
    if params.SUPPRESS_MIN_PASSING <= 0 or not trip_paths:
        return list(features), 0
    stretches: list[tuple[int, bool, int]] = []  # feature, at head, vertices in the stretch
    probes: list[MapFeature] = []
    by_type: dict[ElementType, list[Member]] = {}
    for group in members.values():
        for m in group:
            by_type.setdefault(m.instance.type, []).append(m)
    type_points = {t: TypePoints(ms, params.OUTPUT_SPACING_M / 2) for t, ms in by_type.items()}
    for k, f in enumerate(features):
        group = members.get(f.feature_id, ())
        p = np.asarray(f.points_xy_world, float)
        if (
            f.type.is_polygon
            or f.type in params.WHOLE_ELEMENT_TYPES
            or len(p) < 3
            or "derived" in f.properties
            or len({m.trip_key for m in group}) < 2
            or f.type not in type_points
        ):
            continue
        for at_head in (True, False):
            run = _end_run(type_points[f.type], p, at_head)
            if run is None:
                break  # no vertex that two trips cover: the whole line is the ghost test's
            n, seen_by = run
            part = p[: n + 1] if at_head else p[len(p) - n - 1 :]
            if n < 1 or arclength(part)[-1] < min_length_m:
                continue
            stretches.append((k, at_head, n))
            probes.append(
                MapFeature(
                    f.type,
                    part,
                    f.style,
                    f"{f.feature_id}-tail",
                    {"trips": seen_by, "support_trips": len(seen_by)},
                )
            )
    if not probes:
        return list(features), 0
    passed = passing_counts(probes, trip_paths, params)
    cut: dict[int, list[tuple[bool, int]]] = {}
    for (k, at_head, n), probe, n_passed in zip(stretches, probes, passed, strict=True):
        if seen_too_rarely(int(probe.properties["support_trips"]), n_passed, params):
            cut.setdefault(k, []).append((at_head, n))
    out = list(features)
    n_cut = 0
    for k, ends in cut.items():
        p = np.asarray(out[k].points_xy_world, float)
        lo = max((n for at_head, n in ends if at_head), default=0)
        hi = len(p) - max((n for at_head, n in ends if not at_head), default=0)
        if hi - lo >= 2:  # (both ends cut to the one vertex two trips cover: left whole)
            out[k] = replace(out[k], points_xy_world=p[lo:hi].copy())
            n_cut += len(ends)
    return out, n_cut
