"""A small ASAM OpenDRIVE (1.4 - 1.6) reader: roads, lanes, links and junctions as frozen dataclasses,
and the geometry evaluated at given arclengths.

Frames and units: the file's inertial frame (x east, y north, metres), headings in radians
counter-clockwise from +x, ``s`` the arclength along a road's reference line (metres) and ``t``
the lateral offset from it (metres, positive to the left of increasing ``s``).

What it reads:
- reference lines (``planView``): ``line``, ``arc``, ``spiral`` (a clothoid: curvature linear in
  ``s``, evaluated with :func:`scipy.special.fresnel`), ``poly3`` (local ``v(u)``, ``u`` found from
  the arclength) and ``paramPoly3`` (``pRange`` ``arcLength`` or ``normalized``);
- ``laneOffset`` records (cubic in ``ds``) and lane sections; lane widths (or, without widths,
  ``border`` records) as cubics in ``ds`` from the section start plus ``sOffset``;
- ``roadMark`` types and their ``sOffset``; the lane type; lane ``predecessor`` / ``successor`` ids;
- road ``predecessor`` / ``successor`` links (road or junction, contact point) and junction
  ``connection`` records with their ``laneLink`` pairs;
- the first ``speed`` record of a road's ``type`` (value and unit as written).
Elevation, superelevation, objects and signals are not read (counts of the latter two are kept).

Why a parser of its own: on PyPI, ``pyxodr`` (0.1.3, 2023) reads neither ``laneOffset`` nor
``roadMark`` and imports matplotlib, rich and lxml at module level; ``opendrive2lanelet`` (1.2.1,
2021) is superseded by ``commonroad-scenario-designer`` (a GUI-sized dependency tree) and needs
``commonroad-io`` and lxml; ``opendriveparser`` and ``pyOpenDRIVE`` are not published; the
``OpenDrive`` package is an unrelated perception framework. The subset needed here fits in this
module over numpy, scipy and the standard library's XML parser.
"""

from __future__ import annotations

import xml.etree.ElementTree as ET
from dataclasses import dataclass
from enum import Enum
from pathlib import Path

import numpy as np
from scipy.special import fresnel

from csr_core.errors import CsrError


class OpenDriveError(CsrError, ValueError):
    """The OpenDRIVE text cannot be read (malformed XML, a missing attribute, an unknown geometry)."""


class GeometryKind(str, Enum):
    LINE = "line"
    ARC = "arc"
    SPIRAL = "spiral"
    POLY3 = "poly3"
    PARAM_POLY3 = "paramPoly3"


class ContactPoint(str, Enum):
    START = "start"
    END = "end"


@dataclass(frozen=True, slots=True)
class Cubic:
    """``a + b ds + c ds^2 + d ds^3`` valid from ``s_m`` (``ds = s - s_m``; metres)."""

    s_m: float
    a: float
    b: float
    c: float
    d: float

    def __call__(self, s_m: np.ndarray) -> np.ndarray:
        ds = np.asarray(s_m, float) - self.s_m
        return self.a + ds * (self.b + ds * (self.c + ds * self.d))


def piecewise_cubic(records: tuple[Cubic, ...], s_m: np.ndarray, default: float = 0.0) -> np.ndarray:
    """Evaluate records sorted by ``s_m`` (each valid up to the next); ``default`` without records."""
    s_m = np.asarray(s_m, float)
    out = np.full(s_m.shape, default)
    if not records:
        return out
    starts = np.array([r.s_m for r in records])
    # before the first record: the first one extrapolated (files start their records at 0)
    k = np.clip(np.searchsorted(starts, s_m + 1e-9, side="right") - 1, 0, len(records) - 1)
    for i, rec in enumerate(records):
        mask = k == i
        if mask.any():
            out[mask] = rec(s_m[mask])
    return out


@dataclass(frozen=True, slots=True)
class Geometry:
    """One ``planView`` record: start pose ``(x_m, y_m, hdg_rad)`` at ``s_m``, ``length_m`` long.

    ``params`` by kind: arc ``(curvature_1pm,)``; spiral ``(curv_start_1pm, curv_end_1pm)``;
    poly3 ``(a, b, c, d)``; paramPoly3 ``(aU, bU, cU, dU, aV, bV, cV, dV, normalized)``.
    """

    s_m: float
    x_m: float
    y_m: float
    hdg_rad: float
    length_m: float
    kind: GeometryKind
    params: tuple[float, ...] = ()


@dataclass(frozen=True, slots=True)
class RoadMark:
    s_offset_m: float  # from the lane section start
    type: str  # OpenDRIVE roadMark type: "solid", "broken", "solid solid", "none", "curb", ...
    color: str = "standard"


@dataclass(frozen=True, slots=True)
class Lane:
    """One lane of a section. ``widths`` / ``borders`` are cubics in ``ds`` from the section start
    (their ``s_m`` is the record's ``sOffset``); the road marks describe the lane's outer edge
    (for the centre lane 0: the reference line shifted by the lane offset)."""

    lane_id: int
    type: str
    widths: tuple[Cubic, ...] = ()
    borders: tuple[Cubic, ...] = ()
    road_marks: tuple[RoadMark, ...] = ()
    predecessor_id: int | None = None
    successor_id: int | None = None


@dataclass(frozen=True, slots=True)
class LaneSection:
    s_m: float
    lanes: tuple[Lane, ...]  # left (positive ids, descending), centre (0), right (negative, descending)

    def lane(self, lane_id: int) -> Lane | None:
        for lane in self.lanes:
            if lane.lane_id == lane_id:
                return lane
        return None


@dataclass(frozen=True, slots=True)
class RoadLink:
    element_type: str  # "road" or "junction"
    element_id: str
    contact_point: ContactPoint | None  # of the linked road; None for a junction


@dataclass(frozen=True, slots=True)
class Road:
    road_id: str
    name: str
    length_m: float
    junction_id: str  # "-1" outside junctions
    predecessor: RoadLink | None
    successor: RoadLink | None
    geometries: tuple[Geometry, ...]
    lane_offsets: tuple[Cubic, ...]
    sections: tuple[LaneSection, ...]
    speed_max: float | None = None  # as written in the file, see ``speed_unit``
    speed_unit: str = "m/s"
    n_objects: int = 0
    n_signals: int = 0

    @property
    def in_junction(self) -> bool:
        return self.junction_id != "-1"

    def section_end_m(self, index: int) -> float:
        return self.sections[index + 1].s_m if index + 1 < len(self.sections) else self.length_m


@dataclass(frozen=True, slots=True)
class Connection:
    incoming_road: str
    connecting_road: str
    contact_point: ContactPoint  # the end of the connecting road that touches the incoming road
    lane_links: tuple[tuple[int, int], ...]  # (incoming lane id, connecting lane id)


@dataclass(frozen=True, slots=True)
class Junction:
    junction_id: str
    name: str
    connections: tuple[Connection, ...]


@dataclass(frozen=True)
class OpenDrive:
    roads: dict[str, Road]
    junctions: dict[str, Junction]
    rev: tuple[int, int] = (1, 4)  # revMajor, revMinor of the header


# --- reading ----------------------------------------------------------------------------------


def _f(el: ET.Element, name: str, default: float | None = None) -> float:
    value = el.get(name)
    if value is None:
        if default is None:
            raise OpenDriveError(f"<{el.tag}> lacks attribute {name!r}")
        return default
    try:
        return float(value)
    except ValueError as exc:
        raise OpenDriveError(f"<{el.tag}> attribute {name}={value!r} is not a number") from exc


def _cubic(el: ET.Element, s_name: str) -> Cubic:
    return Cubic(_f(el, s_name, 0.0), _f(el, "a", 0.0), _f(el, "b", 0.0), _f(el, "c", 0.0), _f(el, "d", 0.0))


def _geometry(el: ET.Element) -> Geometry:
    start = (_f(el, "s"), _f(el, "x"), _f(el, "y"), _f(el, "hdg"), _f(el, "length"))
    if el.find("line") is not None:
        return Geometry(*start, GeometryKind.LINE)
    if (arc := el.find("arc")) is not None:
        return Geometry(*start, GeometryKind.ARC, (_f(arc, "curvature"),))
    if (spiral := el.find("spiral")) is not None:
        return Geometry(*start, GeometryKind.SPIRAL, (_f(spiral, "curvStart"), _f(spiral, "curvEnd")))
    if (poly := el.find("poly3")) is not None:
        return Geometry(*start, GeometryKind.POLY3, tuple(_f(poly, k, 0.0) for k in "abcd"))
    if (pp := el.find("paramPoly3")) is not None:
        coeffs = [_f(pp, k + axis, 0.0) for axis in "UV" for k in "abcd"]
        normalized = 1.0 if pp.get("pRange", "normalized") == "normalized" else 0.0
        return Geometry(*start, GeometryKind.PARAM_POLY3, (*coeffs, normalized))
    raise OpenDriveError(f"geometry at s={start[0]} has no known primitive: {[c.tag for c in el]}")


def _link(el: ET.Element | None) -> RoadLink | None:
    if el is None:
        return None
    cp = el.get("contactPoint")
    return RoadLink(el.get("elementType", "road"), el.get("elementId", ""), ContactPoint(cp) if cp else None)


def _lane(el: ET.Element) -> Lane:
    link = el.find("link")
    pred = link.find("predecessor") if link is not None else None
    succ = link.find("successor") if link is not None else None
    return Lane(
        lane_id=int(el.get("id", "0")),
        type=el.get("type", "none"),
        widths=tuple(sorted((_cubic(w, "sOffset") for w in el.findall("width")), key=lambda c: c.s_m)),
        borders=tuple(sorted((_cubic(b, "sOffset") for b in el.findall("border")), key=lambda c: c.s_m)),
        road_marks=tuple(
            sorted(
                (
                    RoadMark(_f(m, "sOffset", 0.0), m.get("type", "none"), m.get("color", "standard"))
                    for m in el.findall("roadMark")
                ),
                key=lambda m: m.s_offset_m,
            )
        ),
        predecessor_id=int(pred.get("id", "0")) if pred is not None else None,
        successor_id=int(succ.get("id", "0")) if succ is not None else None,
    )


def _section(el: ET.Element) -> LaneSection:
    lanes: list[Lane] = []
    for side in ("left", "center", "right"):
        side_el = el.find(side)
        if side_el is not None:
            lanes.extend(_lane(lane) for lane in side_el.findall("lane"))
    lanes.sort(key=lambda lane: -lane.lane_id)
    return LaneSection(_f(el, "s", 0.0), tuple(lanes))


def _road(el: ET.Element) -> Road:
    link = el.find("link")
    plan = el.find("planView")
    lanes_el = el.find("lanes")
    if plan is None or lanes_el is None:
        raise OpenDriveError(f"road {el.get('id')!r} lacks planView or lanes")
    speed = el.find("type/speed")
    objects, signals = el.find("objects"), el.find("signals")
    return Road(
        road_id=el.get("id", ""),
        name=el.get("name", ""),
        length_m=_f(el, "length"),
        junction_id=el.get("junction", "-1"),
        predecessor=_link(link.find("predecessor") if link is not None else None),
        successor=_link(link.find("successor") if link is not None else None),
        geometries=tuple(sorted((_geometry(g) for g in plan.findall("geometry")), key=lambda g: g.s_m)),
        lane_offsets=tuple(
            sorted((_cubic(o, "s") for o in lanes_el.findall("laneOffset")), key=lambda c: c.s_m)
        ),
        sections=tuple(sorted((_section(s) for s in lanes_el.findall("laneSection")), key=lambda s: s.s_m)),
        speed_max=_f(speed, "max")
        if speed is not None and speed.get("max") not in (None, "no limit")
        else None,
        speed_unit=speed.get("unit", "m/s") if speed is not None else "m/s",
        n_objects=len(objects.findall("object")) if objects is not None else 0,
        n_signals=len(signals.findall("signal")) if signals is not None else 0,
    )


def _junction(el: ET.Element) -> Junction:
    connections = tuple(
        Connection(
            incoming_road=c.get("incomingRoad", ""),
            connecting_road=c.get("connectingRoad", ""),
            contact_point=ContactPoint(c.get("contactPoint", "start")),
            lane_links=tuple(
                (int(ll.get("from", "0")), int(ll.get("to", "0"))) for ll in c.findall("laneLink")
            ),
        )
        for c in el.findall("connection")
    )
    return Junction(el.get("id", ""), el.get("name", ""), connections)


def parse_opendrive(source: str | Path) -> OpenDrive:
    """Read an OpenDRIVE file (a path) or document (a string starting with ``<``)."""
    try:
        text = (
            source
            if isinstance(source, str) and source.lstrip().startswith("<")
            else Path(source).read_text()
        )
        root = ET.fromstring(text)
    except ET.ParseError as exc:
        raise OpenDriveError(f"not well-formed OpenDRIVE XML: {exc}") from exc
    if root.tag != "OpenDRIVE":
        raise OpenDriveError(f"root element is <{root.tag}>, not <OpenDRIVE>")
    header = root.find("header")
    rev = (
        (int(header.get("revMajor", "1")), int(header.get("revMinor", "4"))) if header is not None else (1, 4)
    )
    roads = {r.road_id: r for r in (_road(el) for el in root.findall("road"))}
    junctions = {j.junction_id: j for j in (_junction(el) for el in root.findall("junction"))}
    return OpenDrive(roads, junctions, rev)


# --- geometry ---------------------------------------------------------------------------------


def _clothoid_xy(c: float, t: np.ndarray) -> np.ndarray:
    """Points of the standard clothoid (curvature ``c t``, heading ``c t^2 / 2``) at arclengths ``t``."""
    scale = np.sqrt(np.pi / abs(c))
    s_frac, c_frac = fresnel(t / scale)
    return np.column_stack([scale * c_frac, np.sign(c) * scale * s_frac])


def _local_pose(g: Geometry, ds: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Points ``(N, 2)`` and headings ``(N,)`` in the geometry's start frame (start at the origin,
    heading 0) at arclengths ``ds`` from its start."""
    if g.kind == GeometryKind.LINE:
        return np.column_stack([ds, np.zeros_like(ds)]), np.zeros_like(ds)
    if g.kind == GeometryKind.ARC:
        (k,) = g.params
        if abs(k) < 1e-12:
            return np.column_stack([ds, np.zeros_like(ds)]), np.zeros_like(ds)
        return np.column_stack([np.sin(k * ds) / k, (1.0 - np.cos(k * ds)) / k]), k * ds
    if g.kind == GeometryKind.SPIRAL:
        k0, k1 = g.params
        rate = (k1 - k0) / g.length_m if g.length_m > 0 else 0.0
        if abs(rate) < 1e-12:
            return _local_pose(Geometry(0, 0, 0, 0, g.length_m, GeometryKind.ARC, (k0,)), ds)
        t0 = k0 / rate  # where the standard clothoid has the start curvature
        p = _clothoid_xy(rate, t0 + ds) - _clothoid_xy(rate, np.array([t0]))
        rot = -rate * t0**2 / 2.0  # rotate the clothoid's heading at t0 to 0
        cr, sr = np.cos(rot), np.sin(rot)
        xy = np.column_stack([cr * p[:, 0] - sr * p[:, 1], sr * p[:, 0] + cr * p[:, 1]])
        return xy, k0 * ds + rate * ds**2 / 2.0
    if g.kind == GeometryKind.POLY3:
        a, b, c, d = g.params
        u_dense = np.linspace(0.0, 2.0 * g.length_m + 1.0, 4001)
        dv = b + 2 * c * u_dense + 3 * d * u_dense**2
        s_dense = np.concatenate([[0.0], np.cumsum(np.hypot(1.0, (dv[1:] + dv[:-1]) / 2) * np.diff(u_dense))])
        u = np.interp(ds, s_dense, u_dense)
        v = a + u * (b + u * (c + u * d))
        return np.column_stack([u, v]), np.arctan(b + 2 * c * u + 3 * d * u**2)
    # paramPoly3
    au, bu, cu, du, av, bv, cv, dv_, normalized = g.params
    p_end = 1.0 if normalized else g.length_m
    p_dense = np.linspace(0.0, p_end, 4001)
    u_d = au + p_dense * (bu + p_dense * (cu + p_dense * du))
    v_d = av + p_dense * (bv + p_dense * (cv + p_dense * dv_))
    s_dense = np.concatenate([[0.0], np.cumsum(np.hypot(np.diff(u_d), np.diff(v_d)))])
    s_dense *= g.length_m / s_dense[-1] if s_dense[-1] > 0 else 1.0
    p = np.interp(ds, s_dense, p_dense)
    u = au + p * (bu + p * (cu + p * du))
    v = av + p * (bv + p * (cv + p * dv_))
    hdg = np.arctan2(bv + 2 * cv * p + 3 * dv_ * p**2, bu + 2 * cu * p + 3 * du * p**2)
    return np.column_stack([u, v]), hdg


def reference_pose(road: Road, s_m: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Reference-line points ``(N, 2)`` (file frame, metres) and headings ``(N,)`` (rad) at ``s_m``."""
    s_m = np.atleast_1d(np.asarray(s_m, float))
    if not road.geometries:
        raise OpenDriveError(f"road {road.road_id!r} has no geometry")
    starts = np.array([g.s_m for g in road.geometries])
    k = np.clip(np.searchsorted(starts, s_m + 1e-9, side="right") - 1, 0, len(starts) - 1)
    xy = np.zeros((len(s_m), 2))
    hdg = np.zeros(len(s_m))
    for i, g in enumerate(road.geometries):
        mask = k == i
        if not mask.any():
            continue
        local_xy, local_hdg = _local_pose(g, s_m[mask] - g.s_m)
        c, s = np.cos(g.hdg_rad), np.sin(g.hdg_rad)
        xy[mask] = np.column_stack(
            [g.x_m + c * local_xy[:, 0] - s * local_xy[:, 1], g.y_m + s * local_xy[:, 0] + c * local_xy[:, 1]]
        )
        hdg[mask] = g.hdg_rad + local_hdg
    return xy, hdg


def lane_edges_t(road: Road, section_index: int, s_m: np.ndarray) -> dict[int, tuple[np.ndarray, np.ndarray]]:
    """Lateral offsets ``t`` (metres, left positive) of each lane's inner and outer edge at ``s_m``
    (inside the section): ``{lane_id: (inner_t, outer_t)}``; the centre lane 0 maps to the lane
    offset twice."""
    section = road.sections[section_index]
    s_m = np.asarray(s_m, float)
    ds = s_m - section.s_m
    offset = piecewise_cubic(road.lane_offsets, s_m)
    edges: dict[int, tuple[np.ndarray, np.ndarray]] = {0: (offset, offset)}
    for sign in (1, -1):
        inner = offset
        side = sorted((ln for ln in section.lanes if ln.lane_id * sign > 0), key=lambda ln: abs(ln.lane_id))
        for lane in side:
            if lane.widths:
                outer = inner + sign * piecewise_cubic(lane.widths, ds)
            else:
                outer = offset + sign * piecewise_cubic(lane.borders, ds)
            edges[lane.lane_id] = (inner, outer)
            inner = outer
    return edges


def points_at_t(road: Road, s_m: np.ndarray, t_m: np.ndarray) -> np.ndarray:
    """File-frame points ``(N, 2)`` at arclengths ``s_m`` and lateral offsets ``t_m`` (left positive)."""
    xy, hdg = reference_pose(road, s_m)
    normal = np.column_stack([-np.sin(hdg), np.cos(hdg)])
    return xy + normal * np.asarray(t_m, float)[:, None]
