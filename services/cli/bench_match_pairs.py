"""`csr bench-match-pairs`: the time of ``GET /v1/tiles/{z}/{x}/{y}/match-pairs`` for one tile of
``--pairs`` match pairs, on the embedded default (a fresh SQLite file) and, with
``--database-url``, on PostGIS (an empty PostGIS database, as for ``csr bench-tiles``).

For each deployment: the pairs are written into one zoom-16 tile (records shaped like the align
job's: 12 element matches each, centres spread over the tile), a fresh ``csr serve`` is started,
and ``--repeat`` keep-alive requests of the whole listing in one page (``limit`` = the number of
pairs) and of its pages of 100 are timed over HTTP. Prints the median and the worst request.
"""

from __future__ import annotations

import argparse
import os
import random
import secrets
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

from services.cli.bench_ingest import _free_port, _percentile

TILE = (16, 34322, 22423)  # Karlsruhe
PAGE = 100


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("bench-match-pairs", help="time the match-pairs listing of a tile of N pairs")
    p.add_argument("--pairs", type=int, default=1000, help="match pairs in the tile (default 1000)")
    p.add_argument("--repeat", type=int, default=20, help="requests per measurement (default 20)")
    p.add_argument(
        "--database-url",
        default=os.environ.get("CSR_BENCH_DATABASE_URL"),
        help="an empty PostGIS database for the PostGIS row (default CSR_BENCH_DATABASE_URL; none: skipped)",
    )
    p.set_defaults(func=_run)


def write_pairs(
    db_url: str, n: int, *, tile: tuple[int, int, int] = TILE, seed: int = 1, decimals: int = 6
) -> list[str]:
    """``n`` active match pairs in ``tile``, as the align job stores them (confidences rounded to
    ``decimals``: few decimals make ties); returns their ids."""
    import numpy as np
    from sqlalchemy import insert

    from csr_core.geo import tile_bounds_lonlat
    from services.db.engine import make_engine, make_session_factory, migrate
    from services.db.models import MatchPair, utcnow
    from services.tile_frames import tile_frame

    engine = make_engine(db_url)
    migrate(engine)
    west, south, east, north = tile_bounds_lonlat(*tile)
    (x_min, y_min), (x_max, y_max) = tile_frame(*tile).to_local(np.array([[west, south], [east, north]]))
    rng = random.Random(seed)
    rows: list[dict[str, Any]] = []
    for i in range(n):
        confidence = round(rng.random(), decimals)
        record = {
            "submap_i": i,
            "submap_j": i + 1,
            "trip_key_i": f"veh-1__t{i}@{i}",
            "trip_key_j": f"veh-2__t{i}@0",
            "frames_i": [0, 40],
            "frames_j": [5, 55],
            "centre_xy_world": [rng.uniform(x_min, x_max), rng.uniform(y_min, y_max)],
            "relative_pose_xyyaw": [rng.gauss(0, 1), rng.gauss(0, 1), rng.gauss(0, 0.02)],
            "confidence": confidence,
            "residual_rms_m": rng.uniform(0.05, 0.5),
            "instance_matches": [[k, k] for k in range(12)],
            "match_confidences": [0.9] * 12,
            "pose_graph_inlier": True,
            "human": False,
        }
        rows.append(
            {
                "id": f"{seed:04d}-{i:08d}-{rng.getrandbits(32):08x}",
                "z": tile[0],
                "x": tile[1],
                "y": tile[2],
                "job_id": "bench",
                "trip_pk_i": f"trip-{i}",
                "trip_pk_j": f"trip-{i + 1}",
                "confidence": confidence,
                "residual_rms_m": record["residual_rms_m"],
                "status": "active",
                "record": record,
                "created_at": utcnow(),
            }
        )
    with make_session_factory(engine).begin() as session:
        session.execute(insert(MatchPair), rows)
    engine.dispose()
    return [row["id"] for row in rows]


def _serve(env: dict[str, str], port: int) -> subprocess.Popen:
    import httpx

    csr = Path(sys.executable).parent / "csr"
    proc = subprocess.Popen(
        [str(csr), "serve", "--port", str(port), "--no-access-log"],
        env=env,
        stdout=subprocess.DEVNULL,
        stderr=subprocess.DEVNULL,
    )
    deadline = time.monotonic() + 120
    while time.monotonic() < deadline:
        try:
            if httpx.get(f"http://127.0.0.1:{port}/healthz", timeout=1).status_code == 200:
                return proc
        except httpx.HTTPError:
            time.sleep(0.2)
    proc.kill()
    raise RuntimeError("csr serve did not start")


def _timed(http, url: str, params: dict, repeat: int) -> tuple[list[float], int]:
    """Seconds of ``repeat`` requests of ``url`` (after one warm-up) and the pairs of the last."""
    http.get(url, params=params).raise_for_status()
    seconds, n = [], 0
    for _ in range(repeat):
        started = time.perf_counter()
        answer = http.get(url, params=params).raise_for_status()
        seconds.append(time.perf_counter() - started)
        n = len(answer.json()["match_pairs"])
    return seconds, n


def _pages(http, url: str) -> tuple[float, int, int]:
    """Seconds, pages and pairs of walking every page of ``PAGE`` pairs via ``next``."""
    started, pages, pairs = time.perf_counter(), 0, 0
    next_url: str | None = url + f"?limit={PAGE}"
    while next_url:
        body = http.get(next_url).raise_for_status().json()
        pages, pairs, next_url = pages + 1, pairs + len(body["match_pairs"]), body["next"]
    return time.perf_counter() - started, pages, pairs


def measure(name: str, db_url: str, data_dir: Path, args: argparse.Namespace) -> str:
    import httpx

    write_pairs(db_url, args.pairs)
    key = "bench-" + secrets.token_hex(12)
    env = {k: v for k, v in os.environ.items() if not k.startswith("CSR_")}
    env.update({"CSR_DATA_DIR": str(data_dir), "CSR_ADMIN_KEY": key, "CSR_EMBEDDED_WORKERS": "0"})
    if not db_url.startswith("sqlite"):
        env["CSR_DATABASE_URL"] = db_url
    port = _free_port()
    server = _serve(env, port)
    try:
        with httpx.Client(
            base_url=f"http://127.0.0.1:{port}", headers={"Authorization": f"Bearer {key}"}, timeout=120
        ) as http:
            url = "/v1/tiles/{}/{}/{}/match-pairs".format(*TILE)
            whole, n = _timed(http, url, {"limit": args.pairs}, args.repeat)
            page, _ = _timed(http, url, {"limit": PAGE}, args.repeat)
            walk_s, pages, walked = _pages(http, url)
    finally:
        server.terminate()
        server.wait(timeout=30)
    return (
        f"| {name} | {n} | {_percentile(whole, 0.5) * 1e3:.1f} / {max(whole) * 1e3:.1f} | "
        f"{_percentile(page, 0.5) * 1e3:.1f} / {max(page) * 1e3:.1f} | {walk_s * 1e3:.0f} ({pages} pages, {walked}) |"
    )


def _run(args: argparse.Namespace) -> int:
    import logging

    logging.getLogger("httpx").setLevel(logging.WARNING)
    lines = [
        "| deployment | pairs in one page | one page of all: median / max ms | a page of 100: median / max ms "
        "| every page of 100 via next: ms |",
        "| --- | ---: | ---: | ---: | ---: |",
    ]
    with tempfile.TemporaryDirectory(prefix="csr-bench-pairs-") as tmp:
        sqlite_url = f"sqlite:///{Path(tmp) / 'data' / 'csr.sqlite3'}"
        lines.append(measure("embedded (SQLite)", sqlite_url, Path(tmp) / "data", args))
        if args.database_url:
            lines.append(measure("PostGIS", args.database_url, Path(tmp) / "pg", args))
    print("\n".join(lines))  # noqa: T201 (the command's output)
    return 0
