"""Hand-made synthetic trips with known answers (unit tests, quick benchmarks).

A straight or constant-curvature road, parallel lines at fixed lateral offsets from its
reference curve, a vehicle driving along one lane; GNSS, odometry and BEV perception simulated
with seeded noise. Deliberately simple: the fleet simulator (``csr_core.sim``) is the realistic one.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from csr_core import se2
from csr_core.geo import LocalFrame
from csr_core.types import DividerStyle, ElementType, GnssStatus, PerceivedElement, Trip


@dataclass(frozen=True)
class SynthLine:
    type: ElementType
    offset_m: float  # lateral offset from the road reference curve (left positive)
    s_range_m: tuple[float, float] = (-1e9, 1e9)
    style: DividerStyle | None = None
    dash_m: tuple[float, float] | None = None  # (dash, gap): perceive dashes as separate pieces


@dataclass(frozen=True)
class SynthCrossing:
    """A stop line (a line) or crosswalk (a rectangle) across the road at arclength ``s_m``,
    from lateral offset ``from_m`` to ``to_m``; perceived whole, in frames that hold all of it."""

    type: ElementType
    s_m: float
    from_m: float
    to_m: float
    width_m: float = 4.0  # along the road (crosswalks)


@dataclass(frozen=True)
class SynthSpec:
    length_m: float = 300.0
    speed_mps: float = 10.0
    rate_hz: float = 10.0
    curvature_1pm: float = 0.0
    heading_rad: float = 0.3
    vehicle_offset_m: float = 1.75
    lines: tuple[SynthLine, ...] = (
        SynthLine(ElementType.ROAD_BOUNDARY, -1.9),
        SynthLine(ElementType.LANE_DIVIDER, 1.75, style=DividerStyle.DASHED),
        SynthLine(ElementType.LANE_DIVIDER, 5.25, style=DividerStyle.SOLID),
        SynthLine(ElementType.ROAD_BOUNDARY, 8.9),
    )
    bev_x_m: tuple[float, float] = (-15.0, 30.0)
    bev_y_m: tuple[float, float] = (-15.0, 15.0)
    point_spacing_m: float = 2.0
    gnss_sigma_m: float = 0.0
    gnss_bias_m: tuple[float, float] = (0.0, 0.0)
    gnss_status: GnssStatus = GnssStatus.RTK_FLOAT
    report_std: bool = True
    gnss_jumps: tuple[tuple[int, int, float, float], ...] = ()  # (first, last, dx, dy) frames
    gnss_outages: tuple[tuple[int, int], ...] = ()  # (first, last) frames with status none
    odom_sigma_per_m: float = 0.0
    odom_yaw_sigma_per_m: float = 0.0
    element_sigma_m: float = 0.0
    ghosts: tuple[tuple[int, int, int, float], ...] = ()  # (first, last, line index, shift m)
    crossings: tuple[SynthCrossing, ...] = ()
    origin_lonlat: tuple[float, float] = (11.58, 48.137)
    seed: int = 0
    extra: dict = field(default_factory=dict)


def _curve(s: np.ndarray, kappa: float, heading0: float) -> np.ndarray:
    """Reference curve poses (x, y, yaw) at arclength s."""
    yaw = heading0 + kappa * s
    if abs(kappa) < 1e-12:
        x, y = s * np.cos(heading0), s * np.sin(heading0)
    else:
        x = (np.sin(yaw) - np.sin(heading0)) / kappa
        y = -(np.cos(yaw) - np.cos(heading0)) / kappa
    return np.stack([x, y, yaw], axis=-1)


def line_points_world(spec: SynthSpec, line: SynthLine, spacing_m: float = 0.25) -> np.ndarray:
    s0 = max(line.s_range_m[0], -40.0)
    s1 = min(line.s_range_m[1], spec.length_m + 40.0)
    s = np.arange(s0, s1 + 1e-9, spacing_m)
    ref = _curve(s, spec.curvature_1pm, spec.heading_rad)
    normal = np.stack([-np.sin(ref[:, 2]), np.cos(ref[:, 2])], axis=1)
    return ref[:, :2] + line.offset_m * normal


def crossing_points_world(spec: SynthSpec, crossing: SynthCrossing) -> np.ndarray:
    """World outline of a crosswalk ``(4, 2)``, or the two ends of a stop line ``(2, 2)``."""
    half = crossing.width_m / 2 if crossing.type == ElementType.CROSSWALK else 0.0
    out = []
    for ds, offset in (
        (-half, crossing.from_m),
        (-half, crossing.to_m),
        (half, crossing.to_m),
        (half, crossing.from_m),
    ):
        ref = _curve(np.array([crossing.s_m + ds]), spec.curvature_1pm, spec.heading_rad)[0]
        out.append(ref[:2] + offset * np.array([-np.sin(ref[2]), np.cos(ref[2])]))
    return np.array(out if half else out[:2])


def make_trip(spec: SynthSpec) -> tuple[Trip, np.ndarray, LocalFrame]:
    """Returns (trip, true world_T_vehicle poses (N, 3), the local frame)."""
    rng = np.random.default_rng(spec.seed)
    frame = LocalFrame(origin_lat=spec.origin_lonlat[1], origin_lon=spec.origin_lonlat[0])
    n = int(spec.length_m / spec.speed_mps * spec.rate_hz) + 1
    t = np.arange(n) / spec.rate_hz
    s = t * spec.speed_mps
    ref = _curve(s, spec.curvature_1pm, spec.heading_rad)
    normal = np.stack([-np.sin(ref[:, 2]), np.cos(ref[:, 2])], axis=1)
    true = np.column_stack([ref[:, :2] + spec.vehicle_offset_m * normal, ref[:, 2]])

    # odometry: true increments with noise, integrated from an arbitrary origin
    incr = se2.between(true[:-1], true[1:])
    d = np.linalg.norm(incr[:, :2], axis=1)
    incr[:, :2] += rng.normal(size=(n - 1, 2)) * (spec.odom_sigma_per_m * d)[:, None]
    incr[:, 2] += rng.normal(size=n - 1) * spec.odom_yaw_sigma_per_m * d
    odom = np.zeros((n, 3))
    odom[0] = (5.0, -3.0, 1.0)
    for i in range(n - 1):
        odom[i + 1] = se2.compose(odom[i], incr[i])

    gnss_xy = true[:, :2] + np.asarray(spec.gnss_bias_m) + rng.normal(size=(n, 2)) * spec.gnss_sigma_m
    status = np.full(n, int(spec.gnss_status), dtype=np.uint8)
    for a, b, dx, dy in spec.gnss_jumps:
        gnss_xy[a : b + 1] += (dx, dy)
    for a, b in spec.gnss_outages:
        status[a : b + 1] = GnssStatus.NONE
    std = np.full(n, max(spec.gnss_sigma_m, 0.02) if spec.report_std else np.nan)
    heading = np.full(n, np.nan)

    lines_world = [line_points_world(spec, ln) for ln in spec.lines]
    elements = []
    for i in range(n):
        frame_elems = []
        world_T_veh = true[i]
        veh_T_world = se2.inverse(world_T_veh)
        shifted = [(j, 0.0) for j in range(len(spec.lines))]
        shifted += [(j, sh) for a, b, j, sh in spec.ghosts if a <= i <= b]
        for j, shift in shifted:
            line = spec.lines[j]
            pts = se2.transform_points(veh_T_world, lines_world[j])
            pts = pts + (0.0, shift)
            inside = (
                (pts[:, 0] >= spec.bev_x_m[0])
                & (pts[:, 0] <= spec.bev_x_m[1])
                & (pts[:, 1] >= spec.bev_y_m[0])
                & (pts[:, 1] <= spec.bev_y_m[1])
            )
            if inside.sum() < 2:
                continue
            idx = np.flatnonzero(inside)
            pieces = np.split(idx, np.flatnonzero(np.diff(idx) > 1) + 1)
            for piece in pieces:
                p = pts[piece]
                if line.dash_m is not None:
                    dash, gap = line.dash_m
                    sl = np.arange(len(line_points_world(spec, line)))[piece] * 0.25
                    phase = np.mod(sl, dash + gap) < dash
                    sub = np.split(np.arange(len(p)), np.flatnonzero(np.diff(phase.astype(int)) != 0) + 1)
                    chunks = [p[k] for k in sub if phase[k[0]] and len(k) >= 2]
                else:
                    chunks = [p]
                for c in chunks:
                    step = max(int(round(spec.point_spacing_m / 0.25)), 1)
                    keep = np.r_[np.arange(0, len(c), step), len(c) - 1] if len(c) > 2 else np.arange(len(c))
                    c = c[np.unique(keep)]
                    if len(c) < 2:
                        continue
                    c = c + rng.normal(size=c.shape) * spec.element_sigma_m
                    frame_elems.append(PerceivedElement(line.type, c, style=line.style, score=0.9))
        for crossing in spec.crossings:
            pts = se2.transform_points(veh_T_world, crossing_points_world(spec, crossing))
            if (
                (pts[:, 0] >= spec.bev_x_m[0])
                & (pts[:, 0] <= spec.bev_x_m[1])
                & (pts[:, 1] >= spec.bev_y_m[0])
                & (pts[:, 1] <= spec.bev_y_m[1])
            ).all():
                pts = pts + rng.normal(size=pts.shape) * spec.element_sigma_m
                frame_elems.append(PerceivedElement(crossing.type, pts, score=0.9))
        elements.append(tuple(frame_elems))

    lonlat = frame.to_lonlat(gnss_xy)
    trip = Trip(
        vehicle_id="synth",
        trip_id=f"seed{spec.seed}",
        started_at="2026-11-21T00:00:00Z",
        timestamps_s=t,
        gnss_lonlat_deg=lonlat,
        gnss_status=status,
        gnss_std_m=std,
        gnss_heading_deg=frame.true_heading_deg(heading, lonlat),
        odom_xyyaw=odom,
        elements=tuple(elements),
        sensor_setup={
            "bev_range_m": {"x": list(spec.bev_x_m), "y": list(spec.bev_y_m)},
            "rate_hz": spec.rate_hz,
        },
    )
    return trip, true, frame
