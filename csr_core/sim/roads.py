"""Road building blocks for procedural worlds: a road along a reference line with lanes in
both directions, its dividers and boundaries, and signalised-intersection furniture.

Right-hand traffic: forward lanes lie right of the reference line (negative left offset),
backward lanes left of it, travelling the other way. Lanes are numbered from the centre out.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from csr_core.sim import geometry as geo
from csr_core.sim.world import WorldBuilder
from csr_core.types import DividerStyle, ElementType


@dataclass(frozen=True)
class Road:
    """Lane ids of one built road and its boundary lines (world frame)."""

    forward_lanes: tuple[int, ...]  # centre outward
    backward_lanes: tuple[int, ...]  # centre outward
    reference_xy: np.ndarray  # (M, 2)
    right_boundary_xy: np.ndarray  # (M, 2), offset -(n_fwd * w + shoulder)
    left_boundary_xy: np.ndarray  # (M, 2), offset +(n_bwd * w + shoulder)


def add_styled_line(
    builder: WorldBuilder, points_xy: np.ndarray, style: DividerStyle, solid_mask: np.ndarray | None = None
) -> None:
    """A divider; where ``solid_mask`` (per point) is set a dashed line turns solid (split in pieces)."""
    if solid_mask is None or style != DividerStyle.DASHED or not solid_mask.any():
        builder.add_element(ElementType.LANE_DIVIDER, points_xy, style)
        return
    edges = np.flatnonzero(np.diff(solid_mask.astype(int))) + 1
    for piece in np.split(np.arange(len(points_xy)), edges):
        if len(piece) < 2:
            continue
        lo, hi = piece[0], min(piece[-1] + 1, len(points_xy) - 1)
        piece_style = DividerStyle.SOLID if solid_mask[piece[0]] else DividerStyle.DASHED
        builder.add_element(ElementType.LANE_DIVIDER, points_xy[lo : hi + 1], piece_style)


def add_road(
    builder: WorldBuilder,
    reference_xy: np.ndarray,
    *,
    n_forward: int,
    n_backward: int,
    lane_width_m: float,
    speed_mps: float,
    road_type: str,
    center_style: DividerStyle,
    shoulder_m: float = 0.5,
    edge_lines: bool = False,
    boundaries: bool = True,
    divider_span_m: tuple[float, float] | None = None,
    solid_before_end_m: float = 0.0,
    solid_where_curvature_above_1pm: float | None = None,
) -> Road:
    """Build lanes, centrelines, dividers and (optionally) boundaries along ``reference_xy``.

    ``divider_span_m`` limits painted dividers to an arclength interval (e.g. between stop
    lines); ``solid_before_end_m`` makes lane dividers solid over that distance before the
    end each lane drives towards (approach to a stop line).
    """
    ref = geo.resample(reference_xy, 1.0)
    s = geo.arclength_m(ref)
    w = lane_width_m
    fwd, bwd = [], []
    for i in range(n_forward):
        fwd.append(builder.add_lane(geo.offset(ref, -(i + 0.5) * w), speed_mps, w, road_type))
    for j in range(n_backward):
        bwd.append(builder.add_lane(geo.offset(ref, (j + 0.5) * w)[::-1], speed_mps, w, road_type))
    for lanes in (fwd, bwd):
        for a, b in zip(lanes[:-1], lanes[1:], strict=True):
            builder.neighbours(a, b)

    lo, hi = divider_span_m if divider_span_m is not None else (0.0, s[-1])
    span = (s >= lo - 1e-9) & (s <= hi + 1e-9)
    ref_span, s_span = ref[span], s[span]
    curvy = None
    if solid_where_curvature_above_1pm is not None:
        kappa = np.abs(geo.curvature_1pm(ref_span))
        # widen the no-overtaking zones by ~100 m either side, as painted
        curvy = (
            np.convolve((kappa > solid_where_curvature_above_1pm).astype(float), np.ones(201), mode="same")
            > 0
        )
    if n_forward and n_backward:
        add_styled_line(builder, ref_span, center_style, curvy)
    for i in range(1, n_forward):
        solid = (s_span > hi - solid_before_end_m) if solid_before_end_m > 0 else None
        add_styled_line(builder, geo.offset(ref_span, -i * w), DividerStyle.DASHED, solid)
    for j in range(1, n_backward):
        solid = (s_span < lo + solid_before_end_m) if solid_before_end_m > 0 else None
        add_styled_line(builder, geo.offset(ref_span, j * w), DividerStyle.DASHED, solid)
    if edge_lines:
        if n_forward:
            builder.add_element(
                ElementType.LANE_DIVIDER, geo.offset(ref_span, -n_forward * w), DividerStyle.SOLID
            )
        builder.add_element(
            ElementType.LANE_DIVIDER, geo.offset(ref_span, n_backward * w), DividerStyle.SOLID
        )

    right_b = geo.offset(ref, -(n_forward * w + shoulder_m))
    left_b = geo.offset(ref, n_backward * w + shoulder_m)
    if boundaries:
        builder.add_element(ElementType.ROAD_BOUNDARY, right_b)
        builder.add_element(ElementType.ROAD_BOUNDARY, left_b)
    return Road(tuple(fwd), tuple(bwd), ref, right_b, left_b)


def stop_line(builder: WorldBuilder, at_xy: np.ndarray, travel_dir: np.ndarray, width_m: float) -> None:
    """A stop line across lanes ``width_m`` wide to the right of ``at_xy`` (travel direction unit)."""
    right = np.array([travel_dir[1], -travel_dir[0]])
    builder.add_element(
        ElementType.STOP_LINE, np.array([at_xy + right * 0.2, at_xy + right * (width_m - 0.2)])
    )


def crosswalk(
    builder: WorldBuilder,
    center_xy: np.ndarray,
    along_dir: np.ndarray,
    road_width_m: float,
    depth_m: float = 4.0,
) -> None:
    """A rectangular crosswalk polygon across a road (``along_dir`` is the road direction)."""
    a = np.asarray(along_dir, float) / np.linalg.norm(along_dir)
    n = np.array([-a[1], a[0]])
    hw, hd = road_width_m / 2.0, depth_m / 2.0
    c = np.asarray(center_xy, float)
    corners = np.array([c - a * hd - n * hw, c + a * hd - n * hw, c + a * hd + n * hw, c - a * hd + n * hw])
    builder.add_element(ElementType.CROSSWALK, corners)


def connect_lanes(
    builder: WorldBuilder, lane_in: int, lane_out: int, speed_mps: float, road_type: str
) -> int:
    """A connector lane (Bezier) from the end of ``lane_in`` to the start of ``lane_out``."""
    g = builder.graph
    c_in, c_out = g.nodes[lane_in]["centerline_xy"], g.nodes[lane_out]["centerline_xy"]
    path = geo.bezier_cubic(c_in[-1], geo.tangents(c_in)[-1], c_out[0], geo.tangents(c_out)[0], 1.0)
    lid = builder.add_lane(path, speed_mps, g.nodes[lane_in]["width_m"], road_type)
    builder.connect(lane_in, lid)
    builder.connect(lid, lane_out)
    return lid


def corner_curb(
    builder: WorldBuilder, p0: np.ndarray, d0: np.ndarray, p1: np.ndarray, d1: np.ndarray
) -> None:
    """Curb around an intersection corner from ``p0`` (line direction ``d0``) to ``p1`` (``d1``)."""
    control = geo.line_intersection(p0, d0, p1, d1)
    if control is None or np.linalg.norm(control - p0) > 60 or np.linalg.norm(control - p1) > 60:
        control = (np.asarray(p0) + np.asarray(p1)) / 2.0
    builder.add_element(ElementType.ROAD_BOUNDARY, geo.bezier_quadratic(p0, control, p1, 0.5))
