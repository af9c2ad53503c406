"""Procedural worlds: urban grid, highway with ramps, curvy rural loop, roundabout.

Every world is fixed (its geometry does not depend on the scenario seed) and placed at a
real-looking origin. Dimensions are named constants below, in metres and m/s.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import shapely

from csr_core.sim import geometry as geo
from csr_core.sim.roads import add_road, connect_lanes, corner_curb, crosswalk, stop_line
from csr_core.sim.world import World, WorldBuilder
from csr_core.types import DividerStyle, ElementType

URBAN_ORIGIN_LATLON = (48.1374, 11.5755)  # Munich centre
HIGHWAY_ORIGIN_LATLON = (48.7120, 9.2240)  # near the A8 at Stuttgart
RURAL_ORIGIN_LATLON = (47.9060, 8.1050)  # Black Forest
ROUNDABOUT_ORIGIN_LATLON = (47.9950, 7.8530)  # Freiburg

URBAN_SPEED_MPS = 13.9  # 50 km/h
URBAN_TURN_SPEED_MPS = 7.0
HIGHWAY_SPEED_MPS = 33.3  # 120 km/h
RAMP_SPEED_MPS = 22.2  # 80 km/h
RURAL_SPEED_MPS = 25.0  # 90 km/h
ROUNDABOUT_ARM_SPEED_MPS = 13.9
ROUNDABOUT_RING_SPEED_MPS = 8.0


# --- urban grid -------------------------------------------------------------------------------

URBAN_NX, URBAN_NY = 5, 4  # intersections along x and y
URBAN_SPACING_X_M, URBAN_SPACING_Y_M = 210.0, 170.0
URBAN_AVENUE_LANES, URBAN_AVENUE_LANE_W_M = 2, 3.25  # streets along x: lanes per direction
URBAN_STREET_LANES, URBAN_STREET_LANE_W_M = 1, 3.5  # streets along y
URBAN_SHOULDER_M = 0.5
URBAN_CURB_RADIUS_M = 6.0


@dataclass
class _Arm:
    """One street leaving an intersection (``direction`` points away from its centre)."""

    angle_rad: float
    direction: np.ndarray
    incoming: tuple[int, ...]  # lanes towards the intersection, centre outward
    outgoing: tuple[int, ...]  # lanes away from it, centre outward
    right_curb_xy: np.ndarray  # curb end right of ``direction``
    left_curb_xy: np.ndarray
    extra: dict = field(default_factory=dict)


def _intersection(builder: WorldBuilder, arms: list[_Arm], straight_mps: float, turn_mps: float) -> None:
    """Connector lanes between arms (no U-turns) and corner curbs between consecutive arms."""
    arms = sorted(arms, key=lambda a: a.angle_rad)
    for a_in in arms:
        for a_out in arms:
            if a_in is a_out or not a_in.incoming or not a_out.outgoing:
                continue
            delta = float(np.angle(np.exp(1j * (a_out.angle_rad - a_in.angle_rad - np.pi))))
            if abs(delta) < np.pi / 4:
                pairs = list(zip(a_in.incoming, a_out.outgoing, strict=False))
                speed = straight_mps
            elif delta > 0:
                pairs, speed = [(a_in.incoming[0], a_out.outgoing[0])], turn_mps
            else:
                pairs, speed = [(a_in.incoming[-1], a_out.outgoing[-1])], turn_mps
            for lane_in, lane_out in pairs:
                connect_lanes(builder, lane_in, lane_out, speed, "urban_junction")
    for k, arm in enumerate(arms):
        nxt = arms[(k + 1) % len(arms)]
        if len(arms) == 1:
            break
        corner_curb(builder, arm.left_curb_xy, -arm.direction, nxt.right_curb_xy, -nxt.direction)


def urban_grid() -> World:
    """A 5 x 4 grid of signalised intersections: avenues 2+2 lanes (x), streets 1+1 lanes (y),
    stop lines, crosswalks on every arm, curbs with rounded corners."""
    rng = np.random.default_rng(1001)  # fixed world geometry
    builder = WorldBuilder()
    nodes = {
        (i, j): np.array([i * URBAN_SPACING_X_M, j * URBAN_SPACING_Y_M]) + rng.uniform(-8, 8, 2)
        for j in range(URBAN_NY)
        for i in range(URBAN_NX)
    }
    avenue_hw = URBAN_AVENUE_LANES * URBAN_AVENUE_LANE_W_M + URBAN_SHOULDER_M
    street_hw = URBAN_STREET_LANES * URBAN_STREET_LANE_W_M + URBAN_SHOULDER_M
    arms: dict[tuple[int, int], list[_Arm]] = {k: [] for k in nodes}
    segments = [((i, j), (i + 1, j), True) for j in range(URBAN_NY) for i in range(URBAN_NX - 1)]
    segments += [((i, j), (i, j + 1), False) for i in range(URBAN_NX) for j in range(URBAN_NY - 1)]
    for a, b, is_avenue in segments:
        n_lanes = URBAN_AVENUE_LANES if is_avenue else URBAN_STREET_LANES
        w = URBAN_AVENUE_LANE_W_M if is_avenue else URBAN_STREET_LANE_W_M
        hw = avenue_hw if is_avenue else street_hw
        hw_cross = street_hw if is_avenue else avenue_hw
        pa, pb = nodes[a], nodes[b]
        length = float(np.linalg.norm(pb - pa))
        u = (pb - pa) / length
        left_n = np.array([-u[1], u[0]])
        d_lane, d_stop, d_curb = hw_cross + 1.0, hw_cross + 6.0, hw_cross + URBAN_CURB_RADIUS_M
        ref = np.array([pa + u * d_lane, pb - u * d_lane])
        road = add_road(
            builder,
            ref,
            n_forward=n_lanes,
            n_backward=n_lanes,
            lane_width_m=w,
            speed_mps=URBAN_SPEED_MPS,
            road_type="urban",
            center_style=DividerStyle.DOUBLE if n_lanes > 1 else DividerStyle.DASHED,
            shoulder_m=URBAN_SHOULDER_M,
            boundaries=False,
            divider_span_m=(d_stop - d_lane, length - d_lane - d_stop),
            solid_before_end_m=25.0,
        )
        for lane in road.forward_lanes + road.backward_lanes:
            builder.graph.nodes[lane]["stop_line_before_end_m"] = d_stop - d_lane
        curb_ref = np.array([pa + u * d_curb, pb - u * d_curb])
        for side in (-1.0, 1.0):
            builder.add_element(
                ElementType.ROAD_BOUNDARY,
                geo.resample(geo.offset(geo.resample(curb_ref, 1.0), side * hw), 1.0),
            )
        # furniture at both ends: stop line for the incoming lanes, crosswalk across the road
        for end, direction in ((pa, u), (pb, -u)):
            stop_line(builder, end + direction * d_stop, -direction, n_lanes * w)
            crosswalk(builder, end + direction * (hw_cross + 3.0), direction, 2 * hw - 0.4)
        right_of_u, left_of_u = -left_n * hw, left_n * hw
        arms[a].append(
            _Arm(
                float(np.arctan2(u[1], u[0])),
                u,
                road.backward_lanes,
                road.forward_lanes,
                pa + u * d_curb + right_of_u,
                pa + u * d_curb + left_of_u,
            )
        )
        arms[b].append(
            _Arm(
                float(np.arctan2(-u[1], -u[0])),
                -u,
                road.forward_lanes,
                road.backward_lanes,
                pb - u * d_curb + left_of_u,
                pb - u * d_curb + right_of_u,
            )
        )
    for key in sorted(arms):
        _intersection(builder, arms[key], URBAN_SPEED_MPS, URBAN_TURN_SPEED_MPS)
    canyons = np.array([[*nodes[(1, 1)], 130.0], [*nodes[(3, 2)], 110.0], [*nodes[(4, 0)], 90.0]])
    return builder.build("urban", *URBAN_ORIGIN_LATLON, canyons)


# --- highway ----------------------------------------------------------------------------------

HIGHWAY_LENGTH_M = 4000.0
HIGHWAY_LANES, HIGHWAY_LANE_W_M = 3, 3.75
HIGHWAY_MEDIAN_HALF_M = 2.0
HIGHWAY_SHOULDER_M = 2.5
HIGHWAY_RAMP_OFFSET_M = 220.0  # how far the local road between off- and on-ramp runs from the highway


def _ramp_loop(carriageway_ref: np.ndarray, s_out: float, s_in: float, lane_offset_m: float) -> np.ndarray:
    """Off-ramp at ``s_out`` diverging right, a local road, on-ramp merging at ``s_in``.

    Control points in the carriageway frame (arclength, left offset); works for s_in > s_out.
    """
    ctrl_sn = [
        (s_out - 60, lane_offset_m),
        (s_out, lane_offset_m),
        (s_out + 120, lane_offset_m - 8),
        (s_out + 260, lane_offset_m - 60),
        (s_out + 330, -HIGHWAY_RAMP_OFFSET_M),
        (s_in - 330, -HIGHWAY_RAMP_OFFSET_M),
        (s_in - 260, lane_offset_m - 60),
        (s_in - 120, lane_offset_m - 8),
        (s_in, lane_offset_m),
        (s_in + 60, lane_offset_m),
    ]
    s = np.array([c[0] for c in ctrl_sn])
    n = np.array([c[1] for c in ctrl_sn])
    base = geo.interpolate_at(carriageway_ref, s)
    t = geo.interpolate_at(carriageway_ref, s + 1.0) - geo.interpolate_at(carriageway_ref, s - 1.0)
    t /= np.linalg.norm(t, axis=1, keepdims=True)
    normal = np.column_stack([-t[:, 1], t[:, 0]])
    pts = geo.chaikin(base + normal * n[:, None], 5)
    pts = geo.resample(pts, 1.0)
    # keep the part between the diverge and merge points (the ends were only for tangents)
    s_pts = geo.arclength_m(pts)
    d0 = np.linalg.norm(
        pts - (geo.interpolate_at(carriageway_ref, [s_out]) + normal[1] * lane_offset_m), axis=1
    )
    d1 = np.linalg.norm(
        pts - (geo.interpolate_at(carriageway_ref, [s_in]) + normal[-2] * lane_offset_m), axis=1
    )
    return geo.cut(pts, s_pts[int(np.argmin(d0))], s_pts[int(np.argmin(d1))], 1.0)


def highway() -> World:
    """Two 3-lane carriageways with a median; each direction has an off-ramp (split) leading to
    a local road and an on-ramp (merge) back; turnarounds beyond both ends keep routes going."""
    builder = WorldBuilder()
    x = np.arange(0.0, HIGHWAY_LENGTH_M + 1.0, 5.0)
    centre = geo.resample(np.column_stack([x, 35.0 * np.sin(2 * np.pi * x / 2500.0)]), 1.0)
    w = HIGHWAY_LANE_W_M
    paved, ramps = [], []
    builder.add_element(ElementType.ROAD_BOUNDARY, centre)  # median barrier
    for direction in (+1, -1):
        ref = geo.offset(centre, -HIGHWAY_MEDIAN_HALF_M)
        if direction < 0:
            ref = geo.offset(centre, HIGHWAY_MEDIAN_HALF_M)[::-1]
        total = geo.arclength_m(ref)[-1]
        s_split, s_merge = 1500.0, 2600.0
        cuts = [0.0, s_split, s_merge, total]
        pieces: list[list[int]] = []
        for k in range(3):
            part = geo.cut(ref, cuts[k], cuts[k + 1], 1.0)
            road = add_road(
                builder,
                part,
                n_forward=HIGHWAY_LANES,
                n_backward=0,
                lane_width_m=w,
                speed_mps=HIGHWAY_SPEED_MPS,
                road_type="highway",
                center_style=DividerStyle.SOLID,
                edge_lines=True,
                boundaries=False,
            )
            pieces.append(list(road.forward_lanes))
            if k:
                for a, b in zip(pieces[k - 1], pieces[k], strict=True):
                    builder.connect(a, b)
        outer_offset = -(HIGHWAY_LANES * w + HIGHWAY_SHOULDER_M)
        outer = geo.offset(ref, outer_offset)
        paved.append(shapely.Polygon(np.vstack([ref, outer[::-1]])))
        ramp_xy = _ramp_loop(ref, s_split, s_merge, -(HIGHWAY_LANES - 0.5) * w)
        ramp = builder.add_lane(ramp_xy, RAMP_SPEED_MPS, w, "ramp")
        builder.connect(pieces[0][-1], ramp)  # split
        builder.connect(ramp, pieces[2][-1])  # merge
        ramps.append((ramp_xy, outer))
    # boundaries: outer guard rails interrupted where ramps leave; ramp curbs outside the highway
    highway_area = shapely.union_all(paved).buffer(0.3)
    for ramp_xy, outer in ramps:
        ramp_area = shapely.LineString(ramp_xy).buffer(w / 2 + 1.8)
        _add_lines(builder, shapely.LineString(outer).difference(ramp_area))
        for side in (-1.0, 1.0):
            edge = shapely.LineString(geo.offset(ramp_xy, side * (w / 2 + 1.5)))
            _add_lines(builder, edge.difference(highway_area))
    builder.add_turnarounds(max_gap_m=45.0)
    canyons = np.array([[3200.0, 30.0, 150.0], [800.0, 30.0, 90.0]])  # a bridge section, an overpass
    return builder.build("highway", *HIGHWAY_ORIGIN_LATLON, canyons)


def _add_lines(builder: WorldBuilder, geom: shapely.Geometry, min_length_m: float = 5.0) -> None:
    for part in getattr(geom, "geoms", [geom]):
        if part.is_empty or part.geom_type != "LineString" or part.length < min_length_m:
            continue
        builder.add_element(ElementType.ROAD_BOUNDARY, np.asarray(part.coords)[:, :2])


# --- rural ------------------------------------------------------------------------------------

RURAL_RADIUS_M = 900.0
RURAL_LANE_W_M = 3.25
RURAL_NO_OVERTAKING_CURVATURE_1PM = 1.0 / 350.0


def rural() -> World:
    """A curvy two-lane country road closing on itself (about 6 km): dashed centre line turning
    solid in sharp bends, solid edge lines, asphalt edges as road boundaries."""
    builder = WorldBuilder()
    theta = np.linspace(0.0, 2 * np.pi, 2400, endpoint=False)
    r = RURAL_RADIUS_M * (
        1 + 0.22 * np.sin(3 * theta + 0.5) + 0.08 * np.sin(7 * theta + 1.3) + 0.03 * np.sin(13 * theta)
    )
    loop = np.column_stack([r * np.cos(theta), 0.7 * r * np.sin(theta)])
    loop = geo.resample(np.vstack([loop, loop[:1]]), 1.0)
    total = geo.arclength_m(loop)[-1]
    cuts = np.linspace(0.0, total, 5)
    fwd, bwd = [], []
    for k in range(4):
        part = geo.cut(loop, cuts[k], cuts[k + 1], 1.0)
        road = add_road(
            builder,
            part,
            n_forward=1,
            n_backward=1,
            lane_width_m=RURAL_LANE_W_M,
            speed_mps=RURAL_SPEED_MPS,
            road_type="rural",
            center_style=DividerStyle.DASHED,
            shoulder_m=0.75,
            edge_lines=True,
            solid_where_curvature_above_1pm=RURAL_NO_OVERTAKING_CURVATURE_1PM,
        )
        fwd.append(road.forward_lanes[0])
        bwd.append(road.backward_lanes[0])
    for k in range(4):
        builder.connect(fwd[k], fwd[(k + 1) % 4])
        builder.connect(bwd[(k + 1) % 4], bwd[k])
    canyons = np.array([[*geo.interpolate_at(loop, np.array([total * 0.3]))[0], 250.0]])  # a forest section
    return builder.build("rural", *RURAL_ORIGIN_LATLON, canyons)


# --- roundabout -------------------------------------------------------------------------------

RB_RING_RADIUS_M = 18.0  # lane centre
RB_RING_LANE_W_M = 5.0
RB_ARM_ANGLES_DEG = (0.0, 80.0, 175.0, 265.0)
RB_ARM_LENGTH_M = 450.0
RB_ARM_LANE_W_M = 3.5
RB_ARM_START_RADIUS_M = 30.0
RB_ENTRY_ANGLE_RAD = 0.42  # ring angle between an arm and where its lanes join / leave the ring


def roundabout() -> World:
    """A single-lane roundabout (counter-clockwise) with four 1+1-lane arms, crosswalks on the
    arms, turnarounds at the far ends of the arms."""
    builder = WorldBuilder()
    arms = []
    r_in, r_out = RB_RING_RADIUS_M - RB_RING_LANE_W_M / 2 - 0.5, RB_RING_RADIUS_M + RB_RING_LANE_W_M / 2 + 0.5
    hw = RB_ARM_LANE_W_M + 0.5
    for k, angle_deg in enumerate(RB_ARM_ANGLES_DEG):
        a = np.radians(angle_deg)
        s = np.arange(0.0, RB_ARM_LENGTH_M + 1.0, 1.0)
        heading = a + (0.4 if k % 2 else -0.3) * (s / RB_ARM_LENGTH_M) ** 2
        steps = np.column_stack([np.cos(heading), np.sin(heading)])
        ref = RB_ARM_START_RADIUS_M * np.array([np.cos(a), np.sin(a)]) + np.vstack(
            [[0, 0], np.cumsum(steps[:-1], axis=0)]
        )
        road = add_road(
            builder,
            ref,
            n_forward=1,
            n_backward=1,
            lane_width_m=RB_ARM_LANE_W_M,
            speed_mps=ROUNDABOUT_ARM_SPEED_MPS,
            road_type="urban",
            center_style=DividerStyle.DASHED,
            boundaries=False,
            divider_span_m=(9.0, 1e9),  # the centre line starts after the crosswalk
        )
        ref_d = geo.resample(ref, 1.0)
        for side in (-1.0, 1.0):
            builder.add_element(
                ElementType.ROAD_BOUNDARY, geo.cut(geo.offset(ref_d, side * hw), 2.0, 1e9, 1.0)
            )
        u = ref_d[1] - ref_d[0]
        crosswalk(builder, ref_d[5], u, 2 * hw - 0.4)
        arms.append((a, road, ref_d))
    # ring pieces between the points where lanes leave (a - e) and join (a + e)
    keys = sorted(
        [(a - RB_ENTRY_ANGLE_RAD, "exit", i) for i, (a, _, _) in enumerate(arms)]
        + [(a + RB_ENTRY_ANGLE_RAD, "entry", i) for i, (a, _, _) in enumerate(arms)]
    )
    ring_pieces = []
    for k, (a0, kind, i) in enumerate(keys):
        a1 = keys[(k + 1) % len(keys)][0]
        a1 = a1 + 2 * np.pi if a1 <= a0 else a1
        pts = geo.arc(np.zeros(2), RB_RING_RADIUS_M, a0, a1, 1.0)
        ring_pieces.append(
            (builder.add_lane(pts, ROUNDABOUT_RING_SPEED_MPS, RB_RING_LANE_W_M, "roundabout"), kind, i)
        )
    for k, (lane, kind, i) in enumerate(ring_pieces):
        prev_lane = ring_pieces[k - 1][0]
        builder.connect(prev_lane, lane)
        _, road, _ = arms[i]
        if kind == "exit":
            connect_lanes(builder, prev_lane, road.forward_lanes[0], ROUNDABOUT_RING_SPEED_MPS, "roundabout")
        else:
            connect_lanes(builder, road.backward_lanes[0], lane, ROUNDABOUT_RING_SPEED_MPS, "roundabout")
    builder.add_element(
        ElementType.ROAD_BOUNDARY, geo.arc(np.zeros(2), r_in, 0.0, 2 * np.pi, 1.0)
    )  # closed ring
    for k, (a, _, ref_d) in enumerate(arms):
        a_next, _, ref_next = arms[(k + 1) % len(arms)]
        a_next = a_next + 2 * np.pi if a_next <= a else a_next
        alpha = np.arcsin(min((hw + 4.0) / r_out, 0.9))
        left_start = geo.offset(ref_d, hw)[2]
        right_start_next = geo.offset(ref_next, -hw)[2]
        arc_pts = geo.arc(np.zeros(2), r_out, a + alpha, a_next - alpha, 1.0)
        curb = geo.chaikin(np.vstack([left_start, arc_pts, right_start_next]), 3)
        builder.add_element(ElementType.ROAD_BOUNDARY, geo.resample(curb, 1.0))
    builder.add_turnarounds(max_gap_m=20.0)
    canyons = np.array([[0.0, 0.0, 90.0]])
    return builder.build("roundabout", *ROUNDABOUT_ORIGIN_LATLON, canyons)


__all__ = ["urban_grid", "highway", "rural", "roundabout"]
