"""`csr demo` (the README's first command) on a small world, as a user runs it: a subprocess that
starts its own embedded service, simulates, uploads, processes, scores and draws; then a rerun on the
same data dir (safe: the same trips under the same ids, nothing new to process, the same map), while
the first port is taken (it falls back to a free one); then the serving mode, stopped by Ctrl-C."""

from __future__ import annotations

import contextlib
import os
import re
import signal
import socket
import sqlite3
import subprocess
import time
from pathlib import Path

import httpx
import orjson
import pytest

from tests.integration.conftest import ARTIFACTS, BIN, REPO, free_port, wait_until

pytestmark = pytest.mark.integration

SMALL = ["--world", "urban", "--trips", "3", "--trip-length-m", "400", "--seed", "5"]
PNG_MAGIC = b"\x89PNG\r\n\x1a\n"


def _env() -> dict[str, str]:
    # a developer's CSR_* settings must not leak in: the demo is the embedded default by definition
    env = {k: v for k, v in os.environ.items() if not k.startswith("CSR_")}
    env.update(
        OPENBLAS_NUM_THREADS="1",
        CSR_DATABASE_URL="postgresql+psycopg://nobody@127.0.0.1:1/none",
        CSR_REDIS_URL="redis://127.0.0.1:1/0",
    )
    return env


def _demo(data_dir: Path, port: int, *extra: str, timeout_s: float = 420) -> subprocess.CompletedProcess:
    run = subprocess.run(
        [str(BIN / "csr"), "demo", *SMALL, "--data-dir", str(data_dir), "--port", str(port), *extra],
        capture_output=True,
        text=True,
        timeout=timeout_s,
        env=_env(),
        cwd=REPO,
    )
    ARTIFACTS.mkdir(exist_ok=True)
    log = ARTIFACTS / f"demo-{time.strftime('%H%M%S')}-{port}.log"
    log.write_text(run.stdout + "\n--- stderr ---\n" + run.stderr)
    assert run.returncode == 0, run.stdout[-3000:] + run.stderr[-3000:]
    return run


def _url(stdout: str) -> str:
    found = re.search(r"^\s+viewer\s+(http://127\.0\.0\.1:\d+)/viewer/\s*$", stdout, re.M)
    assert found, stdout
    return found.group(1)


def _rows(data_dir: Path, sql: str) -> list[tuple]:
    with sqlite3.connect(data_dir / "service" / "csr.sqlite3") as conn:
        return conn.execute(sql).fetchall()


def _port_open(port: int) -> bool:
    with socket.socket() as s:
        return s.connect_ex(("127.0.0.1", port)) == 0


def test_demo_runs_end_to_end_and_a_rerun_is_safe(tmp_path):
    data = tmp_path / "demo"
    port = free_port()
    first = _demo(data, port, "--exit")
    out = first.stdout

    # the accuracy table against ground truth, service and baseline side by side
    assert "Accuracy against ground truth: urban-standard-n3-s5, 3 trips" in out
    header = next(line for line in out.splitlines() if line.startswith("| aligned unless raw"))
    assert "CSR service" in header and "GNSS-only" in header
    for label in (
        "trips with poses (coverage)",
        "ATE RMSE raw / aligned [m]",
        "RPE RMSE raw / aligned [m]",
        "mCD raw / aligned [m]",
        "lane_divider: CD [m] / compl / corr [%]",
        "road_boundary: CD [m] / compl / corr [%]",
    ):
        assert re.search(rf"^\| {re.escape(label)}\s+\| \S", out, re.M), label
    scores = orjson.loads((data / "accuracy.json").read_bytes())
    service = scores["CSR service"]
    assert service["trips"] == 3 and service["trips_with_poses"] >= 2, service
    assert service["aligned"]["ate_rmse"] < 2.0 and service["map_aligned"]["mcd"] < 0.6, service
    assert (data / "accuracy.md").read_text().count("\n|") >= 10

    # the figures, as PNGs
    figures = sorted(p.name for p in (data / "figures").glob("*.png"))
    assert figures == ["demo_error_heatmap.png", "demo_map.png", "demo_map_wide.png", "demo_trajectories.png"]
    for name in figures:
        png = (data / "figures" / name).read_bytes()
        assert png.startswith(PNG_MAGIC) and len(png) > 20_000, name

    # the viewer's URL, the ops page and the admin key (the generated one, in the service's data dir)
    assert _url(out) == f"http://127.0.0.1:{port}"
    assert re.search(rf"^\s+ops\s+http://127\.0\.0\.1:{port}/ops/", out, re.M)
    key = (data / "service" / "admin.key").read_text().strip()
    assert re.search(rf"^\s+admin key\s+{re.escape(key)}\s", out, re.M)
    assert not _port_open(port), "--exit left the service running"
    # how to serve the map again after --exit (tests/integration/test_cli.py runs it)
    assert f"csr serve --data-dir {data / 'service'}" in out

    # processed on the embedded default: SQLite file, every job done here, a published map
    assert _rows(data, "SELECT count(*) FROM trips") == [(3,)]
    jobs_before = _rows(data, "SELECT kind, state, count(*) FROM jobs GROUP BY kind, state ORDER BY 1, 2")
    assert {state for _, state, _ in jobs_before} <= {"done", "failed"}, jobs_before
    assert {kind for kind, _, _ in jobs_before} >= {"ingest_trip", "align_tile", "merge_tile"}, jobs_before
    versions_before = _rows(data, "SELECT z, x, y, version FROM tile_versions ORDER BY 1, 2, 3, 4")
    assert versions_before
    ids_before = orjson.loads((data / "trip_ids.json").read_bytes())
    map_before = (data / "results" / "service" / "map.geojson").read_bytes()

    # rerun on the same data dir while the first port is taken: same trips under the same ids,
    # nothing reprocessed, the same map; the service moves to a free port; the key stays
    with socket.socket() as squatter:
        # the closed service's connections may hold the port in TIME_WAIT; a listener still takes it
        squatter.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        squatter.bind(("127.0.0.1", port))
        squatter.listen(1)
        second = _demo(data, port, "--exit")
    out2 = second.stdout
    assert f"port {port} is taken, using" in out2
    assert _url(out2) != f"http://127.0.0.1:{port}"
    assert "starting from an empty" not in out2 and "(reused from the last run)" in out2
    assert "uploaded 3 trips" in out2 and "(0 new, 3 already stored under the same ids)" in out2
    assert orjson.loads((data / "trip_ids.json").read_bytes()) == ids_before
    assert _rows(data, "SELECT count(*) FROM trips") == [(3,)]
    assert (
        _rows(data, "SELECT kind, state, count(*) FROM jobs GROUP BY kind, state ORDER BY 1, 2")
        == jobs_before
    )
    assert _rows(data, "SELECT z, x, y, version FROM tile_versions ORDER BY 1, 2, 3, 4") == versions_before
    assert (data / "results" / "service" / "map.geojson").read_bytes() == map_before
    assert orjson.loads((data / "accuracy.json").read_bytes())["CSR service"] == service
    assert re.search(rf"^\s+admin key\s+{re.escape(key)}\s", out2, re.M)

    # other parameters on the same data dir: a fresh start (one fleet per map), the key kept
    third = _demo(data, free_port(), "--exit", "--no-baseline", "--trips", "2")
    assert "changed since the last run: trips: starting from an empty" in third.stdout
    assert _rows(data, "SELECT count(*) FROM trips") == [(2,)]
    header = next(line for line in third.stdout.splitlines() if line.startswith("| aligned unless raw"))
    assert "CSR service" in header and "GNSS-only" not in header
    assert (data / "service" / "admin.key").read_text().strip() == key


def test_demo_serves_until_ctrl_c(tmp_path):
    """Without --exit the service keeps answering after the results; Ctrl-C (SIGINT) stops both."""
    data = tmp_path / "serving"
    port = free_port()
    log = (tmp_path / "demo.out").open("w+")
    # Ctrl-C must reach the demo even when the test runner itself ignores SIGINT (a background job of
    # a non-interactive shell does, and a child inherits that): the child starts with the default
    proc = subprocess.Popen(
        [
            str(BIN / "csr"),
            "demo",
            *SMALL,
            "--trips",
            "2",
            "--no-baseline",
            "--data-dir",
            str(data),
            "--port",
            str(port),
        ],
        stdout=log,
        stderr=subprocess.STDOUT,
        env=_env(),
        cwd=REPO,
        preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL),
    )
    try:

        def serving() -> bool:
            output = Path(log.name).read_text()
            assert proc.poll() is None, (
                f"the demo exited ({proc.returncode}) before serving:\n{output[-3000:]}"
            )
            return "serving until Ctrl-C" in output

        wait_until(
            serving,
            timeout_s=300,
            interval_s=1.0,
            what=lambda: f"the demo to serve; output:\n{Path(log.name).read_text()[-3000:]}",
        )
        key = (data / "service" / "admin.key").read_text().strip()
        with httpx.Client(
            base_url=f"http://127.0.0.1:{port}", headers={"Authorization": f"Bearer {key}"}
        ) as http:
            assert http.get("/healthz").json()["status"] == "ok"
            summary = http.get("/v1/jobs/summary").json()
            assert summary["queued"] == summary["running"] == summary["dirty_tiles"] == 0, summary
            assert http.get("/viewer/").status_code == 200
        time.sleep(1.5)
        assert proc.poll() is None, "the demo stopped serving by itself"
        proc.send_signal(signal.SIGINT)
        assert proc.wait(timeout=60) == 0, Path(log.name).read_text()[-3000:]
        assert not _port_open(port), "Ctrl-C left the service running"
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
        log.close()


def test_a_killed_demo_does_not_leave_its_service_running(tmp_path):
    """SIGKILL gives the demo no chance to stop ``csr serve``: the kernel does (parent-death signal)."""
    port = free_port()
    script = (
        "import sys, time; from pathlib import Path; from services.cli.demo import start_service; "
        f"s = start_service(Path({str(tmp_path / 'service')!r}), '127.0.0.1', {port}); "
        "print(s.proc.pid, flush=True); time.sleep(600)"
    )
    demo = subprocess.Popen(
        [str(BIN / "python"), "-c", script], stdout=subprocess.PIPE, text=True, env=_env(), cwd=REPO
    )
    serve_pid = None
    try:
        serve_pid = int(demo.stdout.readline())
        assert _port_open(port), "the service did not start"
        demo.kill()
        demo.wait(timeout=10)
        wait_until(
            lambda: not _port_open(port),
            timeout_s=30,
            interval_s=0.2,
            what="the service to stop after its demo was killed",
        )
    finally:
        if demo.poll() is None:
            demo.kill()
            demo.wait()
        if serve_pid is not None:
            with contextlib.suppress(ProcessLookupError):
                os.kill(serve_pid, signal.SIGKILL)
