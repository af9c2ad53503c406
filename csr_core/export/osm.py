"""Lanelet2 OSM XML: writing a ``Lanelet2Map``, and a validator of the format's rules that
needs no ``lanelet2`` package (ids unique, references resolve, every lanelet has one left and
one right way on the correct sides, bounds running the same way without crossing, plausible
widths; lanelets that share an end point and share not the whole end are listed apart as
``half_joined``: a gap in routing, not a broken file)."""

from __future__ import annotations

import math
import xml.etree.ElementTree as ET
from dataclasses import dataclass
from xml.sax.saxutils import quoteattr

import numpy as np
import shapely

from csr_core.export.lanelet2 import Lanelet2Map
from csr_core.geo import LocalFrame

MAX_PROBLEMS = 50  # the validator lists at most this many problems (and counts all)


def _tags(tags: tuple[tuple[str, str], ...]) -> str:
    return "".join(f"<tag k={quoteattr(k)} v={quoteattr(v)}/>" for k, v in tags)


def to_osm_xml(m: Lanelet2Map, *, generator: str = "csr") -> bytes:
    """OSM XML 0.6 as Lanelet2's loader reads it. Nodes carry ``ele`` (0: the map is 2-D) and
    ``local_x``/``local_y``: metres in the local transverse Mercator at the origin named in
    the file's leading comment (``m.frame``)."""
    out = [
        "<?xml version='1.0' encoding='UTF-8'?>",
        f"<osm version='0.6' generator={quoteattr(generator)}>",
        f"<!-- csr lanelet2 export; local_x/local_y: metres, +proj=tmerc +lat_0={m.frame.origin_lat!r} "
        f"+lon_0={m.frame.origin_lon!r} +k=1 +ellps=WGS84 -->",
    ]
    if len(m.lonlat_deg):
        lo, hi = m.lonlat_deg.min(axis=0), m.lonlat_deg.max(axis=0)
        out.append(
            f"<bounds minlat='{lo[1]:.9f}' minlon='{lo[0]:.9f}' maxlat='{hi[1]:.9f}' maxlon='{hi[0]:.9f}'/>"
        )
    sigma_abs = m.sigma_abs_m if m.sigma_abs_m is not None else np.full(len(m.node_ids), np.nan)
    for nid, (lon, lat), (x, y), sigma, absolute in zip(
        m.node_ids.tolist(),
        m.lonlat_deg.tolist(),
        m.xy_world.tolist(),
        m.sigma_m.tolist(),
        sigma_abs.tolist(),
        strict=True,
    ):
        sigma_tag = f"<tag k='csr:sigma_m' v='{sigma:.3f}'/>" if math.isfinite(sigma) else ""
        if math.isfinite(absolute):
            sigma_tag += f"<tag k='csr:sigma_abs_m' v='{absolute:.3f}'/>"
        out.append(
            f"<node id='{nid}' visible='true' version='1' lat='{lat:.9f}' lon='{lon:.9f}'>"
            f"<tag k='ele' v='0'/><tag k='local_x' v='{x:.3f}'/><tag k='local_y' v='{y:.3f}'/>{sigma_tag}</node>"
        )
    for w in m.ways:
        nds = "".join(f"<nd ref='{n}'/>" for n in w.node_ids)
        out.append(f"<way id='{w.way_id}' visible='true' version='1'>{nds}{_tags(w.tags)}</way>")
    for r in m.relations:
        mem = "".join(
            f"<member type='{t}' ref='{ref}' role={quoteattr(role)}/>" for t, ref, role in r.members
        )
        out.append(
            f"<relation id='{r.relation_id}' visible='true' version='1'>{mem}{_tags(r.tags)}</relation>"
        )
    out.append("</osm>")
    return ("\n".join(out) + "\n").encode()


@dataclass(frozen=True, slots=True)
class ValidationResult:
    problems: tuple[str, ...]  # the first MAX_PROBLEMS
    n_problems: int
    n_nodes: int
    n_ways: int
    n_lanelets: int
    n_successor_pairs: int  # (a, b): b's bounds start at the very nodes where a's end
    half_joined: tuple[str, ...] = ()  # (a, b) sharing one bound's end node only: no route a -> b

    @property
    def ok(self) -> bool:
        return self.n_problems == 0


def _oriented(left: np.ndarray, right: np.ndarray, one_way: bool) -> tuple[bool, bool]:
    """(invert left, invert right) as Lanelet2's loader orients bounds: the right bound runs
    like the left; both are inverted if the left one is not on the left."""
    inv_r = np.linalg.norm(left[0] - right[-1]) + np.linalg.norm(left[-1] - right[0]) < np.linalg.norm(
        left[0] - right[0]
    ) + np.linalg.norm(left[-1] - right[-1])
    r = right[::-1] if inv_r else right
    d = left[-1] - left[0] + r[-1] - r[0]
    rel = r.mean(axis=0) - left.mean(axis=0)
    if float(d[0] * rel[1] - d[1] * rel[0]) > 0:  # right bound on the left: drive the other way
        return True, not inv_r
    return False, bool(inv_r)


def validate_lanelet2_osm(
    xml_bytes: bytes, *, min_width_m: float = 0.5, max_width_m: float = 10.0
) -> ValidationResult:
    """Check a Lanelet2 OSM file against the format's rules (see the module doc)."""
    problems: list[str] = []
    root = ET.fromstring(xml_bytes)
    ids: dict[str, str] = {}
    nodes: dict[str, tuple[float, float]] = {}
    ways: dict[str, list[str]] = {}
    relations: list[ET.Element] = []
    for el in root:
        if el.tag not in ("node", "way", "relation"):
            continue
        i = el.get("id", "")
        if i in ids:
            problems.append(f"id {i} used by a {ids[i]} and a {el.tag}")
        ids[i] = el.tag
        if el.tag == "node":
            try:
                nodes[i] = (float(el.get("lon", "nan")), float(el.get("lat", "nan")))
            except ValueError:
                problems.append(f"node {i}: lat/lon not numbers")
        elif el.tag == "way":
            ways[i] = [nd.get("ref", "") for nd in el.findall("nd")]
        else:
            relations.append(el)
    frame = LocalFrame.around(np.array(list(nodes.values()))) if nodes else LocalFrame(0.0, 0.0)
    node_keys = list(nodes)
    xy = (
        dict(zip(node_keys, frame.to_local(np.array([nodes[k] for k in node_keys])), strict=True))
        if nodes
        else {}
    )
    for w, refs in ways.items():
        missing = [r for r in refs if r not in nodes]
        if missing:
            problems.append(f"way {w}: nodes {missing[:3]} do not exist")
        if len(refs) < 2:
            problems.append(f"way {w}: fewer than 2 nodes")
    ends: dict[str, tuple[tuple[str, str], tuple[str, str], np.ndarray, np.ndarray]] = {}
    n_lanelets = 0
    for rel in relations:
        rid = rel.get("id", "")
        tags = {t.get("k"): t.get("v") for t in rel.findall("tag")}
        if tags.get("type") != "lanelet":
            continue
        n_lanelets += 1
        roles: dict[str, list[str]] = {}
        for mem in rel.findall("member"):
            roles.setdefault(mem.get("role", ""), []).append(mem.get("ref", ""))
            if mem.get("type") == "way" and mem.get("ref") not in ways:
                problems.append(f"lanelet {rid}: way {mem.get('ref')} does not exist")
        if len(roles.get("left", [])) != 1 or len(roles.get("right", [])) != 1:
            problems.append(f"lanelet {rid}: needs exactly one left and one right way")
            continue
        lw, rw = ways.get(roles["left"][0], []), ways.get(roles["right"][0], [])
        if len(lw) < 2 or len(rw) < 2 or any(n not in xy for n in lw + rw):
            continue
        left, right = np.array([xy[n] for n in lw]), np.array([xy[n] for n in rw])
        inv_l, inv_r = _oriented(left, right, tags.get("one_way") != "no")
        if inv_l:
            left, lw = left[::-1], lw[::-1]
        if inv_r:
            right, rw = right[::-1], rw[::-1]
        for where, (a, b) in (("start", (left[0], right[0])), ("end", (left[-1], right[-1]))):
            width = float(np.linalg.norm(a - b))
            if not min_width_m <= width <= max_width_m:
                problems.append(f"lanelet {rid}: width {width:.2f} m at its {where}")
        if float((left[-1] - left[0]) @ (right[-1] - right[0])) <= 0:
            problems.append(f"lanelet {rid}: bounds run in opposite directions")
        ring = np.vstack([left, right[::-1]])
        if not shapely.Polygon(ring).is_valid:
            problems.append(f"lanelet {rid}: bounds cross (the lanelet outline is not a simple polygon)")
        if tags.get("subtype", "road") != "crosswalk":
            ends[rid] = ((lw[0], rw[0]), (lw[-1], rw[-1]), left[1] - left[0], left[-1] - left[-2])
    # successors: a lanelet starting at one of another's end nodes, running on, starts at both
    starts: dict[str, list[str]] = {}
    for rid, (start, _, _, _) in ends.items():
        for n in start:
            starts.setdefault(n, []).append(rid)
    n_pairs = 0
    half_joined: list[str] = []
    for rid, (_, end, _, dir_end) in ends.items():
        followers = {b for n in end for b in starts.get(n, []) if b != rid}
        for b in sorted(followers):
            if float(dir_end @ ends[b][2]) <= 0:
                continue  # the other direction of travel (a shared, inverted divider)
            start_b = ends[b][0]
            if start_b == end:
                n_pairs += 1
            elif start_b[0] == end[0] or start_b[1] == end[1]:  # (a neighbour shares it crosswise)
                half_joined.append(
                    f"lanelets {rid} -> {b}: share the end node of one bound, not of the other"
                )
    return ValidationResult(
        tuple(problems[:MAX_PROBLEMS]),
        len(problems),
        len(nodes),
        len(ways),
        n_lanelets,
        n_pairs,
        tuple(half_joined),
    )
