"""`csr bench-storage`: stored bytes per km of uploaded trips as passes of one route accumulate.

A fresh embedded deployment (``services.local_deployment``) takes ``--passes`` straight trips of
``--trip-length-m`` over the same road (one zoom-16 tile, each with its own sensor noise), in
batches of ``--batch``: each batch is uploaded and processed (``POST /v1/process``, ingest, align,
merge: one new tile version per batch). After the passes listed in ``--at``, the database's bytes
are read per table from SQLite's ``dbstat`` (pages of the table and its indexes) and divided by
the uploaded kilometres. The raw uploads (``trip_uploads``) are left out: retention deletes them
(``CSR_RAW_RETENTION_DAYS``).
"""

from __future__ import annotations

import argparse
import secrets
import sys
import time
from typing import Any

SECTION = "storage"


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("bench-storage", help="stored bytes per km as passes of one route accumulate")
    p.add_argument("--passes", type=int, default=50, help="trips over the route in all (default 50)")
    p.add_argument("--batch", type=int, default=5, help="trips uploaded and processed together (default 5)")
    p.add_argument("--at", default="5,50", help="passes after which the bytes are measured (default 5,50)")
    p.add_argument("--trip-length-m", type=float, default=250.0, help="length of each trip (default 250)")
    p.add_argument("--write", metavar="MARKDOWN", help="write the section into this file (BENCHMARKS.md)")
    p.set_defaults(func=_run)


def table_bytes(db_path: str) -> dict[str, int]:
    """Bytes of each table of a SQLite file, its indexes included (``dbstat``)."""
    import sqlite3

    with sqlite3.connect(db_path) as conn:
        owner = dict(
            conn.execute("SELECT name, tbl_name FROM sqlite_master WHERE type IN ('table', 'index')")
        )
        out: dict[str, int] = {}
        for name, size in conn.execute("SELECT name, sum(pgsize) FROM dbstat GROUP BY name"):
            table = owner.get(name, name)
            out[table] = out.get(table, 0) + int(size)
    return out


def _wait_idle(http, timeout_s: float = 3600.0) -> None:
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        s = http.get("/v1/jobs/summary").raise_for_status().json()
        if s["queued"] == 0 and s["running"] == 0:
            return
        time.sleep(0.5)
    raise RuntimeError("the deployment did not finish its jobs")


def _run(args: argparse.Namespace) -> int:
    import orjson

    from services.cli.bench_common import publish
    from services.cli.bench_ingest import straight_trip
    from services.fleet import client_for
    from services.local_deployment import LocalDeployment

    at = sorted({int(v) for v in args.at.split(",")})
    rows: list[dict[str, Any]] = []
    t0 = time.perf_counter()
    with LocalDeployment("embedded") as dep, client_for(dep.base_url, dep.admin_key) as http:
        db_path = dep.effective_database_url.removeprefix("sqlite:///")
        done = 0
        while done < args.passes:
            n = min(args.batch, args.passes - done)
            for k in range(done, done + n):
                doc = straight_trip(
                    vehicle_id=f"veh-{k % 7}",
                    trip_id=f"pass-{k}-{secrets.token_hex(3)}",
                    length_m=args.trip_length_m,
                    heading_deg=270.0,
                    seed=k,
                )
                http.post(
                    "/v1/trips", content=orjson.dumps(doc), headers={"Content-Type": "application/json"}
                ).raise_for_status()
            done += n
            _wait_idle(http)
            http.post("/v1/process").raise_for_status()
            _wait_idle(http)
            print(f"[{time.perf_counter() - t0:6.0f} s] {done} passes processed", file=sys.stderr)
            if done in at:
                import sqlalchemy as sa

                engine = sa.create_engine(dep.effective_database_url)
                with engine.connect() as conn:
                    km = float(conn.execute(sa.text("SELECT sum(length_km) FROM trips")).scalar() or 0.0)
                    n_versions = int(
                        conn.execute(sa.text("SELECT count(*) FROM tile_versions")).scalar() or 0
                    )
                engine.dispose()
                sizes = table_bytes(db_path)
                rows.append({"passes": done, "km": km, "versions": n_versions, "sizes": sizes})
    section = render(rows, args)
    publish(section, args.write, SECTION, "bench-storage")
    return 0


def render(rows: list[dict[str, Any]], args: argparse.Namespace) -> str:
    tables = sorted(
        {t for r in rows for t in r["sizes"] if t != "trip_uploads"},
        key=lambda t: -max(r["sizes"].get(t, 0) for r in rows),
    )
    head = "| table | " + " | ".join(f"after {r['passes']} passes" for r in rows) + " |"
    lines = [
        "## Storage per km as passes accumulate (`csr bench-storage`)",
        "",
        f"One route, {args.trip_length_m:g} m trips, processed in batches of {args.batch} (one tile version "
        "per batch), embedded SQLite; bytes per uploaded km of each table with its indexes (`dbstat`), "
        "raw uploads (`trip_uploads`, deleted by `CSR_RAW_RETENTION_DAYS`) left out. Regenerate: "
        f"`csr bench-storage --passes {args.passes} --batch {args.batch} --at {args.at} --write BENCHMARKS.md`.",
        "",
        head,
        "| --- |" + " ---: |" * len(rows),
    ]
    for t in tables:
        cells = [f"{r['sizes'].get(t, 0) / r['km']:,.0f}" for r in rows]
        lines.append(f"| {t} | " + " | ".join(cells) + " |")
    totals = [sum(v for k, v in r["sizes"].items() if k != "trip_uploads") / r["km"] for r in rows]
    lines.append("| **total, bytes/km** | " + " | ".join(f"**{v:,.0f}**" for v in totals) + " |")
    lines.append(
        "| raw uploads (left out), bytes/km | "
        + " | ".join(f"{r['sizes'].get('trip_uploads', 0) / r['km']:,.0f}" for r in rows)
        + " |"
    )
    lines.append(
        "| uploaded km / tile versions | "
        + " | ".join(f"{r['km']:.2f} / {r['versions']}" for r in rows)
        + " |"
    )
    if len(totals) >= 2:
        lines += ["", f"Ratio of the last to the first total: {totals[-1] / totals[0]:.2f} (target <= 1.2)."]
    return "\n".join(lines) + "\n"
