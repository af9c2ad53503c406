"""The Lanelet2 benchmark: per world, the export of the truth map and of the pipeline's map,
loaded with the ``lanelet2`` package and judged by Lanelet2's validator checks
(``csr_core.export.lanelet2_checks``) and its routing graph (German vehicle rules).

``csr bench-lanelet2`` simulates a small fleet per world (``OUT/<world>``), runs
``csr reconstruct``'s pipeline on it (``OUT/<world>/rec``; both kept and reused when the fleet
matches) and writes the table of :func:`lanelet2_table`.
"""

from __future__ import annotations

import json
import subprocess
import tempfile
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

from csr_core.bench.runner import csr_command
from csr_core.bench.tables import markdown_table
from csr_core.export import export_lanelet2_geojson
from csr_core.export.lanelet2_checks import check_lanelet2_map, load_lanelet2, routing_figures

#: the simulator's benchmark worlds: five real Lanelet2 / OpenDRIVE maps and the procedural grid
WORLDS = ("karlsruhe", "kashiwanoha", "carcarana", "a9", "newmarket", "urban")


def truth_map(world: str) -> dict:
    """The world's truth map as GeoJSON (what ``csr simulate`` writes to ``truth/map.geojson``)."""
    from csr_core.geo import LocalFrame
    from csr_core.sim.scenario import truth_map_geojson
    from csr_core.sim.worlds import load_world

    w = load_world(world)
    return truth_map_geojson(w, LocalFrame(w.origin_lat, w.origin_lon))


def pipeline_map(world: str, out_dir: Path, trips: int, seed: int) -> dict:
    """The pipeline's map of ``trips`` simulated trips on ``world`` (``csr simulate`` into
    ``out_dir/<world>``, ``csr reconstruct`` into ``out_dir/<world>/rec``; reused when present for
    the same fleet)."""
    scen = out_dir / world
    meta = scen / "scenario.json"
    fleet_matches = meta.exists() and {
        k: json.loads(meta.read_text()).get(k) for k in ("n_trips", "seed")
    } == {"n_trips": trips, "seed": seed}
    rec = scen / "rec" / "map.geojson"
    if not fleet_matches:
        run = ["simulate", "--world", world, "--trips", str(trips), "--seed", str(seed), "--out", str(scen)]
        subprocess.run(csr_command() + run, check=True, capture_output=True)
        rec.unlink(missing_ok=True)
    if not rec.exists():
        run = ["reconstruct", str(scen), "--out", str(rec.parent), "--no-progress"]
        subprocess.run(csr_command() + run, check=True, capture_output=True)
    return json.loads(rec.read_text())


@dataclass(frozen=True, slots=True)
class Lanelet2Row:
    world: str
    source: str  # truth / pipeline
    lanelets: int
    road_lanelets: int
    areas: int
    regulatory_elements: int
    stop_lines: int
    errors: int
    warnings: int
    nodes_within_1mm: int
    routable_share: float
    largest_scc: int
    with_successor: int
    with_lane_change: int


def lanelet2_row(world: str, source: str, map_geojson: dict, n_sources: int | None = None) -> Lanelet2Row:
    """Export ``map_geojson``, load the file with ``lanelet2``, check it and route on it (from
    ``n_sources`` sampled road lanelets; None: from every one)."""
    xml_bytes, m, _ = export_lanelet2_geojson(map_geojson)
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "map.osm"
        path.write_bytes(xml_bytes)
        lmap, errors = load_lanelet2(path, m.frame.origin_lat, m.frame.origin_lon)
        checks = check_lanelet2_map(lmap, errors)
        routing = routing_figures(lmap, n_sources=n_sources)
    return Lanelet2Row(
        world,
        source,
        checks.lanelets,
        checks.road_lanelets,
        checks.areas,
        checks.regulatory_elements,
        m.report.stop_lines,
        checks.n_errors,
        checks.n_warnings,
        checks.nodes_within_1mm,
        routing.routable_share,
        routing.largest_scc,
        routing.with_successor,
        routing.with_lane_change,
    )


def lanelet2_table(rows: Sequence[Lanelet2Row]) -> str:
    header = (
        "world",
        "map",
        "lanelets (road)",
        "areas",
        "regulatory elements / stop lines",
        "errors",
        "warnings",
        "nodes within 1 mm",
        "road lanelets with a successor / a lane change",
        "routable pairs",
        "largest strongly connected component",
    )
    body = [
        (
            r.world,
            r.source,
            f"{r.lanelets} ({r.road_lanelets})",
            str(r.areas),
            f"{r.regulatory_elements} / {r.stop_lines}",
            str(r.errors),
            str(r.warnings),
            str(r.nodes_within_1mm),
            f"{r.with_successor} / {r.with_lane_change}",
            f"{r.routable_share:.1%}",
            str(r.largest_scc),
        )
        for r in rows
    ]
    return markdown_table(header, body)
