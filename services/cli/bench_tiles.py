"""`csr bench-tiles`: tile serving speed (targets: warm requests/s at least a quarter of
nginx serving the same tile bytes as static files, side by side; cold p99 under 50 ms for a tile
of ~1,000 features), on the embedded (SQLite, Python encoder) and PostGIS (``ST_AsMVT``)
deployments.

For each deployment: a fresh ``csr serve``; tile versions written with
``services.db.versions.write_tile_version`` (what the merge job calls): ``--cold-tiles`` zoom-16
tiles of ``--features`` elements each (lines of 8 vertices and crosswalk polygons). *Cold*: the
first request of each of those tiles (nothing cached in the API process; the database's own cache
is warm; the tiles were rendered when their versions were published, see docs/tiles.md). *Warm*:
``--seconds`` of keep-alive requests of one tile by ``--connections`` concurrent connections (the
tile, its ETag and the key are in the API's fast-path caches), and the same load on nginx serving
that tile's bytes as a static file (one nginx worker, like the one API process). The load
generator is the same for both: one asyncio process (uvloop) with raw keep-alive HTTP/1.1
connections; it shares the machine with the server.

nginx: ``apt-get install -y nginx-light`` (Debian); without it the nginx column says so. The PostGIS
row needs ``--database-url`` naming an empty PostGIS database, e.g.::

    psql -h 127.0.0.1 -U postgres -c 'DROP DATABASE IF EXISTS csr_bench_tiles' -c 'CREATE DATABASE csr_bench_tiles'
    psql -h 127.0.0.1 -U postgres -d csr_bench_tiles -c 'CREATE EXTENSION postgis'
    csr bench-tiles --database-url postgresql+psycopg://postgres@127.0.0.1:5432/csr_bench_tiles
"""

from __future__ import annotations

import argparse
import asyncio
import os
import re
import secrets
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

from services.cli.bench_ingest import _free_port, _percentile

LON, LAT = 8.40, 49.01
_CONTENT_LENGTH = re.compile(rb"(?i)\r\ncontent-length:\s*(\d+)")


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "bench-tiles", help="measure .mvt serving (warm req/s vs nginx, cold p99), both deployments"
    )
    p.add_argument("--features", type=int, default=1000, help="elements per tile (default 1000)")
    p.add_argument("--cold-tiles", type=int, default=40, help="tiles requested once each for cold latency")
    p.add_argument("--seconds", type=float, default=8.0, help="duration of each warm run (default 8)")
    p.add_argument("--connections", type=int, default=8, help="concurrent keep-alive connections (default 8)")
    p.add_argument(
        "--database-url",
        default=os.environ.get("CSR_BENCH_DATABASE_URL"),
        help="an empty PostGIS database for the PostGIS row (default CSR_BENCH_DATABASE_URL; none: skipped)",
    )
    p.set_defaults(func=_run)


# --- data ---------------------------------------------------------------------------------------


def tile_features(tile, n: int, seed: int) -> list:
    """``n`` elements spread over ``tile``: lines of 8 vertices (~40 m) and 1 in 10 a crosswalk."""
    import mercantile
    import numpy as np
    from shapely.geometry import LineString, Polygon

    from services.db.versions import VersionFeature

    rng = np.random.default_rng(seed)
    b = mercantile.bounds(tile)
    width, height = b.east - b.west, b.north - b.south
    types = ("lane_divider", "road_boundary", "centerline", "stop_line")
    out = []
    for i in range(n):
        x0, y0 = b.west + rng.uniform(0.05, 0.85) * width, b.south + rng.uniform(0.05, 0.85) * height
        fid = f"bench-{tile.x}-{tile.y}-{i}"
        props = {"support": int(rng.integers(2, 40)), "sigma_m": round(float(rng.uniform(0.05, 0.5)), 3)}
        if i % 10 == 9:
            w, h = 0.02 * width, 0.01 * height
            geom = Polygon([(x0, y0), (x0 + w, y0), (x0 + w, y0 + h), (x0, y0 + h)])
            out.append(VersionFeature(fid, "crosswalk", None, props, geom))
            continue
        t = np.linspace(0, 1, 8)
        xs = x0 + t * 0.1 * width
        ys = y0 + t * 0.02 * height + rng.normal(0, 0.0005 * height, 8)
        style = "dashed" if i % 4 == 0 else None
        out.append(VersionFeature(fid, types[i % 4], style, props, LineString(np.column_stack([xs, ys]))))
    return out


def write_tiles(db_url: str, tiles: list, n_features: int) -> None:
    from services.db import versions as vs
    from services.db.engine import make_engine, make_session_factory

    engine = make_engine(db_url)
    sessions = make_session_factory(engine)
    for i, tile in enumerate(tiles):
        with sessions.begin() as session:
            vs.write_tile_version(
                session,
                z=tile.z,
                x=tile.x,
                y=tile.y,
                features=tile_features(tile, n_features, seed=i),
                reason="merge",
                job_id=None,
                trips=[],
                corrections=[],
                quality={},
                origin_lat=LAT,
                origin_lon=LON,
                state=None,
                publish=True,
                expected_latest=None,
            )
    engine.dispose()


# --- load ---------------------------------------------------------------------------------------


async def _connection(
    port: int, request: bytes, stop_at: float, latencies: list[float], statuses: dict
) -> None:
    reader, writer = await asyncio.open_connection("127.0.0.1", port)
    try:
        while time.perf_counter() < stop_at:
            t0 = time.perf_counter()
            writer.write(request)
            head = await reader.readuntil(b"\r\n\r\n")
            match = _CONTENT_LENGTH.search(head)
            if match and int(match.group(1)):
                await reader.readexactly(int(match.group(1)))
            latencies.append(time.perf_counter() - t0)
            status = int(head[9:12])
            statuses[status] = statuses.get(status, 0) + 1
    finally:
        writer.close()


def warm_load(port: int, path: str, key: str | None, seconds: float, connections: int) -> dict[str, Any]:
    try:
        import uvloop

        uvloop.install()
    except ImportError:
        pass
    auth = f"Authorization: Bearer {key}\r\n" if key else ""
    request = f"GET {path} HTTP/1.1\r\nHost: 127.0.0.1\r\n{auth}Accept: */*\r\n\r\n".encode()
    latencies: list[float] = []
    statuses: dict[int, int] = {}

    async def main() -> float:
        stop_at = time.perf_counter() + seconds
        t0 = time.perf_counter()
        await asyncio.gather(
            *(_connection(port, request, stop_at, latencies, statuses) for _ in range(connections))
        )
        return time.perf_counter() - t0

    wall = asyncio.run(main())
    return {"rps": len(latencies) / wall, "p50_ms": 1000 * _percentile(latencies, 0.5), "statuses": statuses}


def _wait_http(url: str, proc: subprocess.Popen | None, timeout_s: float = 60.0) -> None:
    import httpx

    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        if proc is not None and proc.poll() is not None:
            raise SystemExit(f"{url}: the server exited with {proc.returncode}")
        try:
            httpx.get(url, timeout=1.0)
            return
        except httpx.HTTPError:
            time.sleep(0.2)
    raise SystemExit(f"{url} did not answer")


# --- nginx --------------------------------------------------------------------------------------


def start_nginx(root: Path, workdir: Path) -> tuple[subprocess.Popen, int] | None:
    binary = shutil.which("nginx") or ("/usr/sbin/nginx" if Path("/usr/sbin/nginx").exists() else None)
    if binary is None:
        return None
    port = _free_port()
    conf = workdir / "nginx.conf"
    conf.write_text(
        f"""worker_processes 1;
daemon off;
pid {workdir}/nginx.pid;
error_log {workdir}/error.log warn;
events {{ worker_connections 1024; }}
http {{
  access_log off;
  client_body_temp_path {workdir}/body; proxy_temp_path {workdir}/proxy; fastcgi_temp_path {workdir}/fastcgi;
  uwsgi_temp_path {workdir}/uwsgi; scgi_temp_path {workdir}/scgi;
  types {{ application/vnd.mapbox-vector-tile mvt; }}
  sendfile on; tcp_nopush on; keepalive_requests 1000000;
  server {{
    listen 127.0.0.1:{port};
    root {root};
    etag on;
    add_header Cache-Control "public, max-age=30";
    add_header Access-Control-Allow-Origin "*";
  }}
}}
"""
    )
    proc = subprocess.Popen(
        [binary, "-c", str(conf), "-p", str(workdir)], stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL
    )
    _wait_http(f"http://127.0.0.1:{port}/", proc, timeout_s=10)
    return proc, port


# --- one deployment -----------------------------------------------------------------------------


def run_deployment(name: str, db_url: str | None, args: argparse.Namespace) -> dict[str, Any]:
    import httpx
    import mercantile

    base = mercantile.tile(LON, LAT, 16)
    tiles = [mercantile.Tile(base.x + i % 8, base.y + i // 8, 16) for i in range(args.cold_tiles + 1)]
    warm_tile, cold_tiles = tiles[0], tiles[1:]
    admin_key = "bench-" + secrets.token_hex(8)
    port = _free_port()
    url = f"http://127.0.0.1:{port}"
    bindir = Path(sys.executable).parent
    with tempfile.TemporaryDirectory() as tmp:
        tmpdir = Path(tmp)
        env = {k: v for k, v in os.environ.items() if not k.startswith("CSR_")}
        env.update(
            {"CSR_ADMIN_KEY": admin_key, "CSR_DATA_DIR": str(tmpdir / "data"), "CSR_QUIET_PERIOD_S": "3600"}
        )
        if db_url:
            env["CSR_DATABASE_URL"] = db_url
        server = subprocess.Popen(
            [str(bindir / "csr"), "serve", "--port", str(port), "--no-access-log"],
            env=env,
            stdout=subprocess.DEVNULL,
            stderr=subprocess.DEVNULL,
        )
        nginx = None
        try:
            _wait_http(url + "/healthz", server)
            t0 = time.perf_counter()
            write_tiles(
                db_url or f"sqlite:///{(tmpdir / 'data' / 'csr.sqlite3').resolve()}", tiles, args.features
            )
            write_s = time.perf_counter() - t0
            with httpx.Client(base_url=url, headers={"Authorization": f"Bearer {admin_key}"}) as http:
                cold_ms = []
                for t in cold_tiles:
                    t1 = time.perf_counter()
                    r = http.get(f"/v1/tiles/{t.z}/{t.x}/{t.y}.mvt")
                    cold_ms.append(1000 * (time.perf_counter() - t1))
                    if r.status_code != 200:
                        raise SystemExit(f"{name}: tile {t} answered {r.status_code}")
                warm_path = f"/v1/tiles/{warm_tile.z}/{warm_tile.x}/{warm_tile.y}.mvt"
                body = http.get(warm_path).raise_for_status().content
                pinned_version = http.get("/v1/tiles.json").json()["map_version"]
            import mapbox_vector_tile

            n_features = len(mapbox_vector_tile.decode(body)["road"]["features"])
            warm = warm_load(port, warm_path, admin_key, args.seconds, args.connections)
            pinned = warm_load(
                port, f"{warm_path}?v={pinned_version}", admin_key, args.seconds, args.connections
            )
            static_root = tmpdir / "static"
            target = static_root / warm_path.lstrip("/")
            target.parent.mkdir(parents=True)
            target.write_bytes(body)
            # nginx's workers run as an unprivileged user: let them reach the file
            for path in (tmpdir, *(p for p in target.parents if tmpdir in p.parents), target):
                path.chmod(0o755)
            started = start_nginx(static_root, tmpdir)
            static = None
            if started is not None:
                nginx, nginx_port = started
                static = warm_load(nginx_port, warm_path, None, args.seconds, args.connections)
        finally:
            for proc in (nginx, server):
                if proc is not None:
                    proc.terminate()
                    proc.wait(timeout=30)
    for label, run in (("live", warm), ("pinned", pinned), ("nginx", static)):
        if run is not None and set(run["statuses"]) != {200}:
            raise SystemExit(f"{name}, {label} run: unexpected statuses {run['statuses']}")
    return {
        "name": name,
        "features": n_features,
        "bytes": len(body),
        "write_s": write_s,
        "cold_p50": _percentile(cold_ms, 0.5),
        "cold_p99": _percentile(cold_ms, 0.99),
        "cold_n": len(cold_ms),
        "warm": warm,
        "pinned": pinned,
        "static": static,
    }


def _run(args: argparse.Namespace) -> int:
    import logging

    logging.getLogger("httpx").setLevel(logging.WARNING)
    load_before = os.getloadavg()[0]
    rows = [run_deployment("embedded (SQLite, Python encoder)", None, args)]
    if args.database_url:
        rows.append(run_deployment("PostGIS (ST_AsMVT)", args.database_url, args))
    lines = [
        f"Tiles of {args.features} elements at zoom 16 (lines of 8 vertices, 1 in 10 a crosswalk polygon); "
        f"{os.cpu_count()} cores shared by the server, nginx and the load generator; load average "
        f"{load_before:.1f} at the start, {os.getloadavg()[0]:.1f} at the end. Warm: {args.seconds:.0f} s of "
        f"keep-alive GETs of one tile over {args.connections} connections (the same asyncio/uvloop client process "
        "for both); the API answers from its fast path (cached key, ETag and body); nginx (1 worker) serves "
        f"the same bytes as a static file. Cold: the first request of each of {args.cold_tiles} tiles, one at a time "
        "(rendered when their versions were published). Write: seconds per `write_tile_version` of one tile. "
        "Reproduce: `csr bench-tiles --database-url <an empty PostGIS database>` (see `services/cli/bench_tiles.py`; "
        "nginx from `apt-get install -y nginx-light`).",
        "",
        "| deployment | features / tile | tile bytes | warm req/s (live URL) | warm req/s (pinned `?v=`) "
        "| nginx static req/s | live / nginx | cold p50 | cold p99 | write s / version |",
        "| --- | ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: |",
    ]
    for r in rows:
        static = r["static"]
        nginx = f"{static['rps']:.0f}" if static else "nginx not installed"
        ratio = f"{r['warm']['rps'] / static['rps']:.2f}" if static else "-"
        lines.append(
            f"| {r['name']} | {r['features']} | {r['bytes']:,} | {r['warm']['rps']:.0f} | {r['pinned']['rps']:.0f} "
            f"| {nginx} | {ratio} | {r['cold_p50']:.1f} ms | {r['cold_p99']:.1f} ms "
            f"| {r['write_s'] / (args.cold_tiles + 1):.2f} |"
        )
    lines.append("")
    verdicts = []
    for r in rows:
        ok_cold = r["cold_p99"] < 50.0
        ok_warm = r["static"] is not None and r["warm"]["rps"] >= r["static"]["rps"] / 4
        warm_text = "n/a (no nginx)" if r["static"] is None else ("met" if ok_warm else "NOT met")
        verdicts.append(
            f"{r['name']}: warm >= nginx/4 {warm_text}; cold p99 < 50 ms {'met' if ok_cold else 'NOT met'}"
        )
    lines.append("Goals: " + "; ".join(verdicts) + ".")
    print("\n".join(lines))
    return 0
