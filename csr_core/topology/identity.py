"""Stable instance ids (kept when the map is rebuilt with more trips).

A fused instance that overlaps a previous map instance of its type (the share of its samples
within the association gate of the previous one, of the shorter of the two, at least
``ID_MIN_OVERLAP_SHARE``) inherits that instance's id; the one-to-one choice is a linear
assignment maximising the overlap. Otherwise it gets a new deterministic id: a hash of its type,
the trip that saw it first and its anchor (first point rounded to a metre).
"""

from __future__ import annotations

import hashlib
from collections.abc import Sequence
from dataclasses import replace

import numpy as np
from scipy.optimize import linear_sum_assignment
from scipy.spatial import cKDTree

from csr_core.single_trip.splicing import resample_polyline
from csr_core.topology.params import TopologyParams
from csr_core.types import ElementType, MapFeature

_PREFIX = {
    ElementType.LANE_DIVIDER: "ld",
    ElementType.ROAD_BOUNDARY: "rb",
    ElementType.CENTERLINE: "cl",
    ElementType.STOP_LINE: "sl",
    ElementType.CROSSWALK: "cw",
    ElementType.ROAD_MARKING: "rm",
}


def new_feature_id(element_type: ElementType, first_trip_key: str, anchor_xy: np.ndarray) -> str:
    """Deterministic id: type prefix + hash of (type, first trip, anchor rounded to 1 m)."""
    ax, ay = (int(round(float(v))) for v in anchor_xy)
    digest = hashlib.sha1(f"{element_type.value}|{first_trip_key}|{ax}|{ay}".encode()).hexdigest()[:12]
    return f"{_PREFIX[element_type]}-{digest}"


def _outline(points_xy: np.ndarray, closed: bool) -> np.ndarray:
    p = np.asarray(points_xy, float)
    return np.vstack([p, p[:1]]) if closed and len(p) >= 3 else p


def overlap_counts(
    new: Sequence[np.ndarray],
    old: Sequence[np.ndarray],
    gate_m: float,
    spacing_m: float,
    closed: bool = False,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``(counts (n_new, n_old), n_samples_new, n_samples_old)``: samples of each new geometry
    within ``gate_m`` of each old one."""
    ns = [resample_polyline(_outline(p, closed), spacing_m) for p in new]
    os_ = [resample_polyline(_outline(p, closed), spacing_m) for p in old]
    counts = np.zeros((len(ns), len(os_)))
    n_new = np.array([len(p) for p in ns], float)
    n_old = np.array([len(p) for p in os_], float)
    if not ns or not os_:
        return counts, n_new, n_old
    old_pts = np.concatenate(os_)
    old_own = np.repeat(np.arange(len(os_)), n_old.astype(int))
    tree = cKDTree(old_pts)
    new_pts = np.concatenate(ns)
    new_own = np.repeat(np.arange(len(ns)), n_new.astype(int))
    hits = tree.query_ball_point(new_pts, gate_m)
    rows = np.repeat(np.arange(len(new_pts)), [len(h) for h in hits])
    cols = np.fromiter((c for h in hits for c in h), dtype=np.int64, count=len(rows))
    if len(rows):  # each new sample counts once per old geometry it is near (1-D keys: a fast unique)
        keys = np.unique(rows * len(os_) + old_own[cols])
        np.add.at(counts, (new_own[keys // len(os_)], keys % len(os_)), 1.0)
    return counts, n_new, n_old


def inherit_ids(
    new_features: Sequence[MapFeature], previous: Sequence[MapFeature], params: TopologyParams
) -> list[str | None]:
    """For each new feature, the id of the previous feature of its type it continues, or None."""
    out: list[str | None] = [None] * len(new_features)
    gate = params.GATE_MAX_SHARE_OF_LANE * params.MIN_LANE_WIDTH_M
    for etype in ElementType:
        ni = [i for i, f in enumerate(new_features) if f.type == etype]
        oi = [j for j, f in enumerate(previous) if f.type == etype and f.feature_id]
        if not ni or not oi:
            continue
        counts, n_new, n_old = overlap_counts(
            [new_features[i].points_xy_world for i in ni],
            [previous[j].points_xy_world for j in oi],
            gate,
            0.5 * params.SAMPLE_SPACING_M,
            closed=etype.is_polygon,
        )
        share = counts / np.maximum(np.minimum(n_new[:, None], n_old[None, :]), 1.0)
        eligible = share >= params.ID_MIN_OVERLAP_SHARE
        if not eligible.any():
            continue
        rows, cols = linear_sum_assignment(np.where(eligible, -counts, 0.0))
        for r, c in zip(rows, cols, strict=True):
            if eligible[r, c]:
                out[ni[r]] = previous[oi[c]].feature_id
    return out


def assign_ids(
    features: list[MapFeature], previous: Sequence[MapFeature], params: TopologyParams
) -> list[MapFeature]:
    """Inherited ids where a previous instance continues, new deterministic ids elsewhere;
    ``first_seen`` keeps the earliest of the previous and the new value."""
    inherited = inherit_ids(features, previous, params)
    prev_by_id = {f.feature_id: f for f in previous}
    used: set[str] = set()
    out = []
    for f, fid in zip(features, inherited, strict=True):
        props = dict(f.properties)
        if fid is not None:
            old = prev_by_id[fid].properties.get("first_seen")
            if old is not None and (props["first_seen"] is None or old < props["first_seen"]):
                props["first_seen"] = old
        else:
            fid = new_feature_id(f.type, props["first_trip"], f.points_xy_world[0])
            base, n = fid, 2
            while fid in used or fid in prev_by_id:
                fid, n = f"{base}-{n}", n + 1
        used.add(fid)
        out.append(replace(f, feature_id=fid, properties=props))
    return out
