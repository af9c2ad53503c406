"""`csr bench-http`: what response compression gains on the map's answers. The bodies are the
ones the service sends for a world's true map (``csr_core.sim``): the ``/v1/map`` GeoJSON of the
whole map, the densest zoom-16 tile as ``.mvt`` (Python encoder) and ``.geojson``, and the
Lanelet2 export; each is compressed with the service's codings and levels
(``services.api.content_coding``). Sizes are exact; times are the best of ``--repeat`` runs."""

from __future__ import annotations

import argparse
import os
import time
from collections import Counter
from typing import Any

from services.cli.bench_common import publish

SECTION = "http-compression"


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("bench-http", help="response sizes and compression times per coding (map answers)")
    p.add_argument("--world", default="karlsruhe", help="the simulator's world whose true map is served")
    p.add_argument("--repeat", type=int, default=5, help="compressions per body and coding (best counts)")
    p.add_argument("--write", metavar="MARKDOWN", help="put the section into this file (BENCHMARKS.md)")
    p.set_defaults(func=_run)


def map_bodies(world_name: str) -> dict[str, bytes]:
    """The service's answers for ``world_name``'s true map, by what they are."""
    import mercantile
    import numpy as np
    import shapely
    from shapely.geometry import shape

    from csr_core.export import export_lanelet2_geojson
    from csr_core.geo import LocalFrame
    from csr_core.sim.scenario import truth_map_geojson
    from csr_core.sim.worlds import load_world
    from services.db import versions as vs
    from services.tiles import mvt
    from services.tiles.mercator import buffered_bounds_lonlat
    from services.tiles.render import feature_collection, feature_json

    world = load_world(world_name)
    truth = truth_map_geojson(world, LocalFrame(world.origin_lat, world.origin_lon))
    features = [
        vs.MapFeature(
            vs.VersionFeature(
                str(f["id"]), f["properties"]["type"], f["properties"].get("style"), {}, shape(f["geometry"])
            ),
            1,
            16,
            0,
            0,
            1,
        )
        for f in truth["features"]
    ]
    vertices = Counter(
        mercantile.tile(lon, lat, 16)
        for f in features
        for lon, lat in np.asarray(getattr(f.feature.geometry, "exterior", f.feature.geometry).coords)
    )
    tile = vertices.most_common(1)[0][0]
    west, south, east, north = buffered_bounds_lonlat(tile.z, tile.x, tile.y, buffer_frac=mvt.BUFFER_FRAC)
    box = shapely.box(west, south, east, north)
    in_tile = [f for f in features if f.feature.geometry.intersects(box)]
    tile_mvt = mvt.encode_python(in_tile, z=tile.z, x=tile.x, y=tile.y)
    assert tile_mvt is not None
    osm, _, _ = export_lanelet2_geojson(truth)
    return {
        f"tile {tile.z}/{tile.x}/{tile.y} .mvt ({len(in_tile)} features)": tile_mvt,
        f"tile {tile.z}/{tile.x}/{tile.y} .geojson": feature_collection([feature_json(f) for f in in_tile]),
        f"/v1/map, whole map ({len(features)} features)": feature_collection(
            [feature_json(f) for f in features]
        ),
        "Lanelet2 export, whole map": osm,
    }


def measure(bodies: dict[str, bytes], repeat: int) -> list[dict[str, Any]]:
    from services.api.content_coding import OFFERED, compress

    rows = []
    for name, body in bodies.items():
        row: dict[str, Any] = {"body": name, "identity": len(body)}
        for coding in OFFERED:
            best_s = float("inf")
            for _ in range(repeat):
                t0 = time.perf_counter()
                packed = compress(body, coding)
                best_s = min(best_s, time.perf_counter() - t0)
            row[coding.value] = (len(packed), best_s * 1e3)
        rows.append(row)
    return rows


def section(rows: list[dict[str, Any]], world: str, repeat: int) -> str:
    from services.api.content_coding import BROTLI_QUALITY, GZIP_LEVEL, OFFERED, ZSTD_LEVEL

    head = "| body | identity bytes | " + " | ".join(f"{c.value} bytes (ratio, ms)" for c in OFFERED) + " |"
    lines = [
        "## Response compression (`csr bench-http`)",
        "",
        f"The service's answers for the `{world}` world's true map, compressed as the service does "
        f"(brotli quality {BROTLI_QUALITY}, zstd level {ZSTD_LEVEL}, gzip level {GZIP_LEVEL}; README, HTTP). "
        f"Ratio: identity / compressed; ms: best of {repeat} compressions on one core of a shared 2-core "
        f"machine (load average {os.getloadavg()[0]:.1f} at the end). An encoded tile is compressed once "
        "per coding and then served from the LRU; bodies from 64 KB on are compressed off the event loop. "
        f"Regenerate: `csr bench-http --write BENCHMARKS.md`.",
        "",
        head,
        "| --- | ---: |" + " ---: |" * len(OFFERED),
    ]
    for row in rows:
        cells = [
            f"{row[c.value][0]:,} ({row['identity'] / row[c.value][0]:.1f}x, {row[c.value][1]:.1f})"
            for c in OFFERED
        ]
        lines.append(f"| {row['body']} | {row['identity']:,} | " + " | ".join(cells) + " |")
    return "\n".join(lines) + "\n"


def _run(args: argparse.Namespace) -> int:
    rows = measure(map_bodies(args.world), args.repeat)
    publish(section(rows, args.world, args.repeat), args.write, SECTION, "bench-http")
    return 0
