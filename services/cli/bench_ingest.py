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
import statistics
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path
from typing import Any

MARK_BEGIN, MARK_END = "<!-- ingest:begin -->", "<!-- ingest:end -->"
EARTH_M_PER_DEG_LAT = 111_320.0


def straight_trip(*, vehicle_id: str, trip_id: str, length_m: float = 1000.0, rate_hz: float = 10.0,
                  speed_mps: float = 10.0, origin_lat: float = 48.1366, origin_lon: float = 11.5790,
                  heading_deg: float = 90.0, seed: int = 0) -> dict[str, Any]:
    """A trip upload (contract section 1) driving straight ``length_m`` at ``speed_mps``, sampled at
    ``rate_hz``, seeing two boundaries, a lane divider and a centerline in every frame (20 points
    each, like the contract example)."""
    import numpy as np

    rng = np.random.default_rng(seed)
    n = int(round(length_m / speed_mps * rate_hz)) + 1
    t_s = np.arange(n) / rate_hz
    along_m = t_s * speed_mps
    heading_rad = math.radians(heading_deg)
    east_m, north_m = along_m * math.sin(heading_rad), along_m * math.cos(heading_rad)
    lat = origin_lat + north_m / EARTH_M_PER_DEG_LAT
    lon = origin_lon + east_m / (EARTH_M_PER_DEG_LAT * math.cos(math.radians(origin_lat)))
    xs = np.linspace(-15.0, 30.0, 20)
    frames = []
    for i in range(n):
        elements = []
        for kind, y_m, track in (("road_boundary", -5.3, 1), ("lane_divider", 1.75, 2),
                                 ("centerline", 5.3, 3), ("road_boundary", 9.0, 4)):
            ys = y_m + rng.normal(0.0, 0.03, xs.size)
            element = {"type": kind, "points": [[round(float(x), 2), round(float(y), 2)] for x, y in zip(xs, ys, strict=True)],
                       "score": round(float(rng.uniform(0.7, 0.95)), 3), "track_id": track}
            if kind == "lane_divider":
                element["style"] = "dashed"
            elements.append(element)
        frames.append({
            "t": round(float(t_s[i]), 3),
            "gnss": {"lat": round(float(lat[i]), 8), "lon": round(float(lon[i]), 8), "status": "rtk_float",
                     "std_m": 0.25, "heading_deg": heading_deg % 360.0},
            "odom": {"x": round(float(along_m[i]), 3), "y": 0.0, "yaw": 0.0},
            "elements": elements,
        })
    return {"schema_version": "1.0", "vehicle_id": vehicle_id, "trip_id": trip_id,
            "started_at": "2026-11-21T08:00:00Z", "sensor_setup": {"model": "bench"}, "frames": frames}


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("bench-ingest", help="measure upload throughput (both deployments) against orjson parsing")
    p.add_argument("--trips", type=int, default=200, help="uploads per deployment (default 200)")
    p.add_argument("--clients", type=int, default=4, help="concurrent clients (default 4)")
    p.add_argument("--database-url", default=os.environ.get("CSR_BENCH_DATABASE_URL"),
                   help="PostGIS URL of an empty database for the distributed run (default: CSR_BENCH_DATABASE_URL; "
                        "none: that run is skipped)")
    p.add_argument("--redis-url", default=os.environ.get("CSR_BENCH_REDIS_URL", "redis://127.0.0.1:6379/13"))
    p.add_argument("--write", type=Path, default=None, help="update this BENCHMARKS.md between the ingest markers")
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


def _upload_all(url: str, admin_key: str, bodies: list[bytes], clients: int) -> tuple[float, list[float], list[int]]:
    import httpx

    latencies: list[float] = []
    statuses: list[int] = []
    lock = threading.Lock()
    next_index = iter(range(len(bodies)))

    def client() -> None:
        headers = {"Authorization": f"Bearer {admin_key}", "Content-Type": "application/json",
                   "Content-Encoding": "gzip"}
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


def _run_deployment(name: str, env_extra: dict[str, str], bodies: list[bytes], clients: int) -> dict[str, Any]:
    admin_key = "bench-" + secrets.token_hex(8)
    port = _free_port()
    url = f"http://127.0.0.1:{port}"
    bindir = Path(sys.executable).parent
    with tempfile.TemporaryDirectory() as data_dir:
        env = {**os.environ, "CSR_ADMIN_KEY": admin_key, "CSR_DATA_DIR": data_dir, "CSR_QUIET_PERIOD_S": "3600",
               **env_extra}
        for var in ("CSR_DATABASE_URL", "CSR_REDIS_URL"):
            if var not in env_extra:
                env.pop(var, None)
        procs = [subprocess.Popen([str(bindir / "csr"), "serve", "--port", str(port), "--no-access-log"], env=env,
                                  stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)]
        try:
            _wait_healthy(url, procs[0])
            if "CSR_REDIS_URL" in env_extra:
                procs.append(subprocess.Popen([str(bindir / "csr"), "worker", "--concurrency", "1"], env=env,
                                              stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL))
            wall_s, latencies, statuses = _upload_all(url, admin_key, bodies, clients)
        finally:
            for proc in procs:
                proc.terminate()
            for proc in procs:
                proc.wait(timeout=30)
    bad = [s for s in statuses if s != 202]
    if bad:
        raise SystemExit(f"{name}: {len(bad)} uploads failed (statuses {sorted(set(bad))})")
    return {"name": name, "wall_s": wall_s, "trips_per_s": len(bodies) / wall_s,
            "p50_ms": 1000 * _percentile(latencies, 0.50), "p99_ms": 1000 * _percentile(latencies, 0.99)}


def _run(args: argparse.Namespace) -> int:
    import orjson

    docs = [straight_trip(vehicle_id=f"veh-{i % 8}", trip_id=f"bench-{i:05d}", seed=i) for i in range(args.trips)]
    plain = [orjson.dumps(doc) for doc in docs]
    bodies = [gzip.compress(b, compresslevel=6) for b in plain]
    mb_plain = sum(map(len, plain)) / 1e6
    mb_sent = sum(map(len, bodies)) / 1e6
    t0 = time.perf_counter()
    for body in plain:
        orjson.loads(body)
    parse_rate = len(plain) / (time.perf_counter() - t0)

    runs = [_run_deployment("embedded (SQLite, in-process jobs)", {}, bodies, args.clients)]
    if args.database_url:
        runs.append(_run_deployment("distributed (PostGIS, Redis, 1 Celery worker)",
                                    {"CSR_DATABASE_URL": args.database_url, "CSR_REDIS_URL": args.redis_url},
                                    bodies, args.clients))
    n_frames = len(docs[0]["frames"])
    lines = [
        f"Workload: {args.trips} trips of 1 km at 10 Hz ({n_frames} frames, {mb_plain / args.trips:.2f} MB JSON, "
        f"{mb_sent / args.trips:.2f} MB gzip each), {args.clients} concurrent clients on loopback, "
        f"`Content-Encoding: gzip`; {os.cpu_count()} cores. Reproduce: `csr bench-ingest --write BENCHMARKS.md` "
        "(set `CSR_BENCH_DATABASE_URL` to an empty PostGIS database for the distributed row).",
        "",
        "| deployment | trips/s | MB/s (JSON) | MB/s (as sent) | p50 latency | p99 latency | share of parse-only rate |",
        "| --- | ---: | ---: | ---: | ---: | ---: | ---: |",
    ]
    for r in runs:
        rate = r["trips_per_s"]
        lines.append(
            f"| {r['name']} | {rate:.1f} | {rate * mb_plain / args.trips:.1f} | {rate * mb_sent / args.trips:.1f} | "
            f"{r['p50_ms']:.0f} ms | {r['p99_ms']:.0f} ms | {rate / parse_rate:.2f} |"
        )
    lines.append(f"| orjson.loads alone, same bodies, 1 thread | {parse_rate:.1f} | {parse_rate * mb_plain / args.trips:.1f} "
                 "| | | | 1.00 |")
    goal = all(r["trips_per_s"] >= parse_rate / 3 for r in runs)
    lines += ["", f"Goal (upload path >= 1/3 of the parse-only rate): {'met' if goal else 'NOT met'} in this run."]
    table = "\n".join(lines)
    print(table)
    if args.write:
        text = args.write.read_text() if args.write.exists() else "# Benchmarks\n"
        block = f"{MARK_BEGIN}\n{table}\n{MARK_END}"
        if MARK_BEGIN in text and MARK_END in text:
            head, rest = text.split(MARK_BEGIN, 1)
            text = head + block + rest.split(MARK_END, 1)[1]
        else:
            text = text.rstrip("\n") + "\n\n## Ingest throughput\n\n" + block + "\n"
        args.write.write_text(text)
    return 0
