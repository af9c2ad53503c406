"""`csr bench-ingest`: ingest throughput of the whole upload path (HTTP, decompress, validate,
store, enqueue) with concurrent clients on loopback, for both deployments, next to the rate at
which orjson alone parses the same bodies. Writes the table into BENCHMARKS.md between
``<!-- ingest:begin -->`` and ``<!-- ingest:end -->``.

Trips are generated here (a straight road, 10 Hz, elements like the contract example), so the
benchmark depends on nothing but the service.
"""

from __future__ import annotations

import argparse
import gzip
import math
import os
import secrets
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path
from typing import Any

MARK_BEGIN, MARK_END = "<!-- ingest:begin -->", "<!-- ingest:end -->"


def straight_trip(
    *,
    vehicle_id: str,
    trip_id: str,
    length_m: float = 1000.0,
    rate_hz: float = 10.0,
    speed_mps: float = 10.0,
    origin_lat: float = 48.1366,
    origin_lon: float = 11.5790,
    heading_deg: float = 90.0,
    seed: int = 0,
) -> dict[str, Any]:
    """A trip upload (contract section 1) driving straight ``length_m`` at ``speed_mps``, sampled at
    ``rate_hz``, seeing two boundaries, a lane divider and a centerline in every frame (20 points
    each, like the contract example)."""
    import numpy as np

    from csr_core.geo import LocalFrame

    rng = np.random.default_rng(seed)
    n = int(round(length_m / speed_mps * rate_hz)) + 1
    t_s = np.arange(n) / rate_hz
    along_m = t_s * speed_mps
    heading_rad = math.radians(heading_deg)
    points_xy_m = np.column_stack([along_m * math.sin(heading_rad), along_m * math.cos(heading_rad)])
    lon, lat = LocalFrame(origin_lat=origin_lat, origin_lon=origin_lon).to_lonlat(points_xy_m).T
    xs = np.linspace(-15.0, 30.0, 20)
    frames = []
    for i in range(n):
        elements = []
        for kind, y_m, track in (
            ("road_boundary", -5.3, 1),
            ("lane_divider", 1.75, 2),
            ("centerline", 5.3, 3),
            ("road_boundary", 9.0, 4),
        ):
            ys = y_m + rng.normal(0.0, 0.03, xs.size)
            element = {
                "type": kind,
                "points": [[round(float(x), 2), round(float(y), 2)] for x, y in zip(xs, ys, strict=True)],
                "score": round(float(rng.uniform(0.7, 0.95)), 3),
                "track_id": track,
            }
            if kind == "lane_divider":
                element["style"] = "dashed"
            elements.append(element)
        frames.append(
            {
                "t": round(float(t_s[i]), 3),
                "gnss": {
                    "lat": round(float(lat[i]), 8),
                    "lon": round(float(lon[i]), 8),
                    "status": "rtk_float",
                    "std_m": 0.25,
                    "heading_deg": heading_deg % 360.0,
                },
                "odom": {"x": round(float(along_m[i]), 3), "y": 0.0, "yaw": 0.0},
                "elements": elements,
            }
        )
    return {
        "schema_version": "1.0",
        "vehicle_id": vehicle_id,
        "trip_id": trip_id,
        "started_at": "2026-11-21T08:00:00Z",
        "sensor_setup": {"model": "bench"},
        "frames": frames,
    }


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "bench-ingest", help="measure upload throughput (both deployments) against orjson parsing"
    )
    p.add_argument("--trips", type=int, default=120, help="uploads per row (default 120)")
    p.add_argument("--clients", type=int, default=4, help="concurrent clients (default 4)")
    p.add_argument(
        "--database-url",
        default=os.environ.get("CSR_BENCH_DATABASE_URL"),
        help="PostGIS URL of an empty database for the distributed run (default: CSR_BENCH_DATABASE_URL; "
        "none: that run is skipped)",
    )
    p.add_argument("--redis-url", default=os.environ.get("CSR_BENCH_REDIS_URL", "redis://127.0.0.1:6379/13"))
    p.add_argument(
        "--write", type=Path, default=None, help="update this BENCHMARKS.md between the ingest markers"
    )
    p.set_defaults(func=_run)


def _percentile(values: list[float], q: float) -> float:
    ordered = sorted(values)
    return ordered[min(len(ordered) - 1, max(0, math.ceil(q * len(ordered)) - 1))]


def _free_port() -> int:
    import socket

    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _wait_healthy(url: str, proc: subprocess.Popen, timeout_s: float = 60.0) -> None:
    import httpx

    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        if proc.poll() is not None:
            raise SystemExit(f"server exited with {proc.returncode}")
        try:
            if httpx.get(url + "/healthz", timeout=1.0).status_code == 200:
                return
        except httpx.HTTPError:
            pass
        time.sleep(0.2)
    raise SystemExit("server did not become healthy")


def _upload_all(
    url: str, admin_key: str, bodies: list[bytes], clients: int
) -> tuple[float, list[float], list[int]]:
    import httpx

    latencies: list[float] = []
    statuses: list[int] = []
    lock = threading.Lock()
    next_index = iter(range(len(bodies)))

    def client() -> None:
        headers = {
            "Authorization": f"Bearer {admin_key}",
            "Content-Type": "application/json",
            "Content-Encoding": "gzip",
        }
        with httpx.Client(base_url=url, headers=headers, timeout=120.0) as http:
            while True:
                with lock:
                    i = next(next_index, None)
                if i is None:
                    return
                t0 = time.perf_counter()
                status = http.post("/v1/trips", content=bodies[i]).status_code
                dt = time.perf_counter() - t0
                with lock:
                    latencies.append(dt)
                    statuses.append(status)

    threads = [threading.Thread(target=client) for _ in range(clients)]
    t0 = time.perf_counter()
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    return time.perf_counter() - t0, latencies, statuses


def _parse_rate(plain: list[bytes]) -> float:
    import orjson

    t0 = time.perf_counter()
    for body in plain:
        orjson.loads(body)
    return len(plain) / (time.perf_counter() - t0)


def _run_deployment(
    name: str,
    env_extra: dict[str, str],
    bodies: list[bytes],
    plain: list[bytes],
    clients: int,
    *,
    with_worker: bool,
) -> dict[str, Any]:
    """One deployment, fresh: the upload run, with the orjson parse-only rate measured just before
    and just after it (the mean is its reference: the machine may be shared)."""
    admin_key = "bench-" + secrets.token_hex(8)
    port = _free_port()
    url = f"http://127.0.0.1:{port}"
    bindir = Path(sys.executable).parent
    with tempfile.TemporaryDirectory() as data_dir:
        env = {
            **os.environ,
            "CSR_ADMIN_KEY": admin_key,
            "CSR_DATA_DIR": data_dir,
            "CSR_QUIET_PERIOD_S": "3600",
            **env_extra,
        }
        for var in ("CSR_DATABASE_URL", "CSR_REDIS_URL"):
            if var not in env_extra:
                env.pop(var, None)
        procs = [
            subprocess.Popen(
                [str(bindir / "csr"), "serve", "--port", str(port), "--no-access-log"],
                env=env,
                stdout=subprocess.DEVNULL,
                stderr=subprocess.DEVNULL,
            )
        ]
        try:
            _wait_healthy(url, procs[0])
            if with_worker:
                procs.append(
                    subprocess.Popen(
                        [str(bindir / "csr"), "worker", "--concurrency", "1"],
                        env=env,
                        stdout=subprocess.DEVNULL,
                        stderr=subprocess.DEVNULL,
                    )
                )
                time.sleep(5)  # the worker is up before the clock starts
            parse_before = _parse_rate(plain)
            wall_s, latencies, statuses = _upload_all(url, admin_key, bodies, clients)
            parse_after = _parse_rate(plain)
        finally:
            for proc in procs:
                proc.terminate()
            for proc in procs:
                proc.wait(timeout=60)
    bad = [s for s in statuses if s != 202]
    if bad:
        raise SystemExit(f"{name}: {len(bad)} uploads failed (statuses {sorted(set(bad))})")
    return {
        "name": name,
        "wall_s": wall_s,
        "trips_per_s": len(bodies) / wall_s,
        "p50_ms": 1000 * _percentile(latencies, 0.50),
        "p99_ms": 1000 * _percentile(latencies, 0.99),
        "parse_per_s": (parse_before + parse_after) / 2,
    }


def _run(args: argparse.Namespace) -> int:
    import logging

    import orjson

    logging.getLogger("httpx").setLevel(logging.WARNING)
    # a few distinct trips (noise seeds), each uploaded under many trip ids
    bases = [
        orjson.dumps(straight_trip(vehicle_id=f"veh-{s}", trip_id="bench-TRIPID", seed=s)) for s in range(4)
    ]
    plain = [
        bases[i % len(bases)].replace(b'"bench-TRIPID"', f'"bench-{i:06d}"'.encode(), 1)
        for i in range(args.trips)
    ]
    n_frames = len(orjson.loads(bases[0])["frames"])
    bodies = [gzip.compress(b, compresslevel=6) for b in plain]
    mb_plain = sum(map(len, plain)) / 1e6
    mb_sent = sum(map(len, bodies)) / 1e6

    runs = []
    for jobs, extra in (("run concurrently", {}), ("deferred", {"CSR_EMBEDDED_WORKERS": "0"})):
        runs.append(
            _run_deployment(
                f"embedded (SQLite) | jobs {jobs} in-process",
                extra,
                bodies,
                plain,
                args.clients,
                with_worker=False,
            )
        )
    if args.database_url:
        distributed = {"CSR_DATABASE_URL": args.database_url, "CSR_REDIS_URL": args.redis_url}
        for with_worker in (True, False):
            _reset_database(args.database_url, args.redis_url)
            jobs = "run concurrently by 1 Celery worker" if with_worker else "queued in Redis, no worker"
            runs.append(
                _run_deployment(
                    f"distributed (PostGIS + Redis) | jobs {jobs}",
                    distributed,
                    bodies,
                    plain,
                    args.clients,
                    with_worker=with_worker,
                )
            )
    lines = [
        f"Workload: {args.trips} trips of 1 km at 10 Hz ({n_frames} frames, {mb_plain / args.trips:.2f} MB JSON, "
        f"{mb_sent / args.trips:.2f} MB gzip each) per row, {args.clients} concurrent clients on loopback, "
        f"`Content-Encoding: gzip`, {os.cpu_count()} cores, load average {os.getloadavg()[0]:.1f} at the end. "
        "Each row is a fresh deployment; the parse-only reference is `orjson.loads` of the same (decompressed) "
        "bodies in one thread, measured just before and after that row's uploads (mean). "
        "Reproduce: `make bench-ingest` (`csr bench-ingest --write BENCHMARKS.md` with `CSR_BENCH_DATABASE_URL` "
        "naming an empty PostGIS database).",
        "",
        "| deployment | jobs during the run | trips/s | MB/s (JSON) | MB/s (as sent) | p50 latency | p99 latency "
        "| orjson parse-only trips/s | upload / parse |",
        "| --- | --- | ---: | ---: | ---: | ---: | ---: | ---: | ---: |",
    ]
    for r in runs:
        rate = r["trips_per_s"]
        lines.append(
            f"| {r['name']} | {rate:.1f} | {rate * mb_plain / args.trips:.1f} | {rate * mb_sent / args.trips:.2f} | "
            f"{r['p50_ms']:.0f} ms | {r['p99_ms']:.0f} ms | {r['parse_per_s']:.1f} | {rate / r['parse_per_s']:.2f} |"
        )
    ratios = [r["trips_per_s"] / r["parse_per_s"] for r in runs]
    below = sum(ratio < 1 / 3 for ratio in ratios)
    lines += [
        "",
        f"Goal (the upload path sustains >= 1/3 of the parse-only rate): "
        f"{'met by every row' if not below else f'NOT met by {below} of {len(runs)} rows'} in this run "
        f"(lowest ratio {min(ratios):.2f}).",
    ]
    table = "\n".join(lines)
    print(table)
    if args.write:
        write_section(args.write, table)
    return 0


def write_section(path: Path, table: str) -> None:
    """Put ``table`` between the ingest markers of ``path``, keeping everything else."""
    text = path.read_text() if path.exists() else "# Benchmarks\n"
    block = f"{MARK_BEGIN}\n{table}\n{MARK_END}"
    if MARK_BEGIN in text and MARK_END in text:
        head, rest = text.split(MARK_BEGIN, 1)
        text = head + block + rest.split(MARK_END, 1)[1]
    else:
        text = text.rstrip("\n") + "\n\n## Ingest throughput\n\n" + block + "\n"
    path.write_text(text)


def _reset_database(database_url: str, redis_url: str) -> None:
    """Empty the benchmark's PostGIS database (all CSR tables) and Redis database between rows."""
    import redis
    import sqlalchemy as sa

    engine = sa.create_engine(database_url)
    with engine.begin() as conn:
        tables = [
            r[0]
            for r in conn.execute(
                sa.text(
                    "SELECT tablename FROM pg_tables WHERE schemaname = 'public' AND tablename <> 'spatial_ref_sys'"
                )
            )
        ]
        for table in tables:
            conn.execute(sa.text(f'DROP TABLE IF EXISTS "{table}" CASCADE'))
    engine.dispose()
    redis.Redis.from_url(redis_url).flushdb()
