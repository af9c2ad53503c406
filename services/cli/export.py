"""`csr export MAP.geojson --out map.osm` / `csr export --scenario-dir DIR --out map.osm`: the
Lanelet2 export of a map GeoJSON (``GET /v1/map`` or ``csr reconstruct``'s ``map.geojson``; a
scenario folder: its reconstruction ``map.geojson`` or else ``truth/map.geojson``), no server.

Prints a summary (lanelets written, skipped by reason, successor links joined); ``--json`` prints
the report as JSON. ``--validate`` checks the file against the format's rules and runs Lanelet2's validator checks
on it (``csr_core.export.lanelet2_checks``: loaded with the ``lanelet2`` package, routing graph
with German vehicle rules); errors fail the command, warnings are listed. Exit 2: bad input;
1: nothing exportable or validation failed.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("export", help="export a map GeoJSON as a Lanelet2 OSM file (no server)")
    p.add_argument("map_geojson", metavar="MAP.geojson", nargs="?", help="FeatureCollection like GET /v1/map")
    p.add_argument(
        "--scenario-dir",
        metavar="DIR",
        help="take DIR/map.geojson (csr reconstruct output) or DIR/truth/map.geojson",
    )
    p.add_argument("--out", required=True, metavar="OUT.osm", help="Lanelet2 OSM file to write")
    p.add_argument(
        "--location", choices=("urban", "nonurban"), default="urban", help="location tag of lanelets"
    )
    p.add_argument(
        "--validate", action="store_true", help="check the file (format rules; Lanelet2 validator checks)"
    )
    p.add_argument("--json", action="store_true", help="print the report as JSON")
    p.set_defaults(func=_run)


def _input_path(args: argparse.Namespace) -> Path:
    if bool(args.map_geojson) == bool(args.scenario_dir):
        raise ValueError("give MAP.geojson or --scenario-dir DIR (one of them)")
    if args.map_geojson:
        return Path(args.map_geojson)
    d = Path(args.scenario_dir)
    for candidate in (d / "map.geojson", d / "truth" / "map.geojson"):
        if candidate.is_file():
            return candidate
    raise ValueError(f"{d}: neither map.geojson nor truth/map.geojson")


def _lanelet2_checks(path: Path, origin_lat: float, origin_lon: float) -> tuple[dict, str]:
    """Lanelet2's validator checks (``csr_core.export.lanelet2_checks``) on the written file and
    routing figures: (report, summary line)."""
    from csr_core.export.lanelet2_checks import check_lanelet2_map, load_lanelet2, routing_figures

    lmap, errors = load_lanelet2(path, origin_lat, origin_lon)
    checks = check_lanelet2_map(lmap, errors)
    if errors:
        return (
            checks.as_dict(),
            f"lanelet2 checks: {checks.n_errors} errors: the file does not load"
            + "".join(f"\n  {i}" for i in checks.issues[:10]),
        )
    routing = routing_figures(lmap)
    report = {**checks.as_dict(), "routing": {k: getattr(routing, k) for k in routing.__slots__}}
    line = (
        f"lanelet2 checks: {checks.n_errors} errors, {checks.n_warnings} warnings "
        f"({', '.join(f'{n} {c}' for c, n in checks.counts_by_check().items()) or 'none'}); "
        f"{checks.lanelets} lanelets, {checks.regulatory_elements} regulatory elements, "
        f"{checks.nodes_within_1mm} nodes within 1 mm; routable pairs {routing.routable_share:.1%}, "
        f"largest strongly connected component {routing.largest_scc} lanelets"
        + "".join(f"\n  {i}" for i in checks.issues[:10])
    )
    return report, line


def _run(args: argparse.Namespace) -> int:
    import orjson

    from csr_core.errors import CsrError
    from csr_core.export import Lanelet2Params, export_lanelet2_geojson, validate_lanelet2_osm

    try:
        path = _input_path(args)
        doc = orjson.loads(path.read_bytes())
        xml_bytes, lmap, ignored = export_lanelet2_geojson(doc, Lanelet2Params(location=args.location))
    except (ValueError, OSError, orjson.JSONDecodeError) as exc:
        print(f"csr export: {exc}", file=sys.stderr)
        return 2
    except CsrError as exc:
        print(f"csr export: {path}: {exc}", file=sys.stderr)
        return 2
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_bytes(xml_bytes)
    r = lmap.report
    report = {"input": str(path), "out": str(out), **r.as_dict(), "input_ignored": ignored}
    status = 0 if r.lanelets else 1
    lines = [
        f"wrote {out}: {r.lanelets} lanelets from {r.lanes} lanes ({r.lanelets_with_virtual_bound} with a virtual "
        f"bound, {r.two_way_lanelets} two-way), {r.crosswalks} crosswalks, {r.stop_lines} stop lines, "
        f"{r.road_markings} road markings; {r.nodes} nodes, {r.ways} ways",
        f"successor links: {r.successor_links_joined}/{r.successor_links} share their junction nodes; "
        f"bridges added: {r.bridges}, seams joined: {r.seams}",
        "skipped: "
        + (", ".join(f"{n} {why}" for why, n in r.runs_skipped.items()) or "nothing")
        + f"; lanes without any lanelet: {r.lanes_skipped}; centrelines too short to be lanes: "
        f"{r.centerlines_not_lanes}; dividers/boundaries bounding no lanelet: {r.lines_unused}",
    ]
    if ignored:
        lines.append("input features ignored: " + ", ".join(f"{n} {why}" for why, n in ignored.items()))
    if args.validate:
        v = validate_lanelet2_osm(xml_bytes)
        report["validation"] = {
            "problems": v.n_problems,
            "first": list(v.problems[:10]),
            "successor_pairs": v.n_successor_pairs,
            "half_joined": len(v.half_joined),
        }
        lines.append(
            f"format check: {v.n_problems} problems, {v.n_lanelets} lanelets, "
            f"{v.n_successor_pairs} successor pairs, {len(v.half_joined)} half-joined (one bound's end "
            "node shared, not the other's: no route)" + "".join(f"\n  {p}" for p in v.problems[:10])
        )
        checks, line = _lanelet2_checks(out, lmap.frame.origin_lat, lmap.frame.origin_lon)
        report["lanelet2"] = checks
        lines.append(line)
        if v.n_problems or checks["errors"]:
            status = 1
    if args.json:
        print(orjson.dumps(report, option=orjson.OPT_INDENT_2).decode())
    else:
        print("\n".join(lines))
    return status
