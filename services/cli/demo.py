"""`csr demo`: watch a fleet build a map (the README's first command, ``make demo``).

    csr demo [--world karlsruhe] [--trips 10] [--trip-length-m 1000] [--seed 1] [--port 8000] [--exit]

The recipe, one step per function below:

1. start ``csr serve`` on the embedded default (SQLite + in-process jobs, no other server) with its
   own data dir ``DATA_DIR/service`` and the admin key generated into it; port ``--port``, or a
   free one if that is taken;
2. simulate a fleet on a world (default: the real Lanelet2 map of Karlsruhe) into ``DATA_DIR/scenario``;
3. upload it over HTTP (progress bar), have it processed (``POST /v1/process``), download the
   service's poses and map (:mod:`services.fleet`);
4. score them against the ground truth (contract section 6) next to the GNSS-only baseline, print
   the table, write ``DATA_DIR/accuracy.md`` / ``.json`` and the figures ``DATA_DIR/figures/*.png``;
5. print the viewer's and the ops page's URLs and the admin key; keep serving until Ctrl-C
   (``--exit``: stop here, for tests and CI).

Reruns are safe and cheap: ``DATA_DIR`` (default ``./data/demo``) is kept, the same parameters give
the same trips (byte-identical for a seed), which the service recognises as already uploaded (200,
the same ids) and already processed; the scenario and the baseline are reused. Other parameters (or
a changed simulator, ``csr_core/sim``) start from an empty ``DATA_DIR`` but for the admin key; so
does ``--fresh``. A changed algorithm (``csr_core``, ``workers``) is only noted: ``--fresh``
recomputes. The demo ignores ``CSR_DATABASE_URL``, ``CSR_REDIS_URL``, ``CSR_ADMIN_KEY`` and ``CSR_DATA_DIR``.
"""

from __future__ import annotations

import argparse
import contextlib
import ctypes
import ctypes.util
import logging
import math
import os
import shutil
import signal
import socket
import subprocess
import sys
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from services.cli.simulate import PROFILES, WORLDS

DEFAULT_DATA_DIR = Path("data/demo")
# The default fleet: 10 trips of 1 km on the Karlsruhe map. Measured on the 2-core dev machine shared
# with other jobs: 100-195 s in all (simulate 4-8 s, upload 4-7 s, processing 66-125 s, GNSS-only
# baseline 7-16 s, scoring and figures ~40 s); a rerun ~50 s.
DEFAULT_TRIPS = 10
DEFAULT_TRIP_LENGTH_M = 1000.0
PROCESS_TIMEOUT_S = 1200.0
SERVER_START_TIMEOUT_S = 90.0
STAMP_FILE = "demo.json"
SERVICE_METHOD = "CSR service"  # the figures' panel title (figures.METHOD_NAMES falls back to it)


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "demo",
        help="start the service (embedded), simulate a fleet, upload and process it, show its accuracy",
        description="Start the service on the embedded default, simulate a fleet, upload it over HTTP, have "
        "it processed, print its accuracy against the ground truth, write figures, print the viewer's URL and "
        "keep serving until Ctrl-C (--exit: stop there). Everything goes under --data-dir; a rerun with the "
        "same parameters reuses it (same trips, same ids, nothing new to process).",
    )
    p.add_argument(
        "--world",
        default="karlsruhe",
        choices=WORLDS,
        help="world to simulate (default: karlsruhe, real Lanelet2)",
    )
    p.add_argument("--trips", type=int, default=DEFAULT_TRIPS, help=f"fleet size (default {DEFAULT_TRIPS})")
    p.add_argument(
        "--trip-length-m",
        type=float,
        default=DEFAULT_TRIP_LENGTH_M,
        help=f"length of each trip in metres (default {DEFAULT_TRIP_LENGTH_M:.0f})",
    )
    p.add_argument(
        "--profile", default="standard", choices=PROFILES, help="sensor error profile (default standard)"
    )
    p.add_argument("--seed", type=int, default=1, help="scenario seed (same seed: same trips)")
    p.add_argument(
        "--data-dir",
        type=Path,
        default=DEFAULT_DATA_DIR,
        help=f"everything the demo writes (default ./{DEFAULT_DATA_DIR})",
    )
    p.add_argument("--host", default="127.0.0.1", help="bind address of the service (default 127.0.0.1)")
    p.add_argument("--port", type=int, default=8000, help="port (default 8000; a free one if taken; 0: any)")
    p.add_argument("--no-baseline", action="store_true", help="skip the GNSS-only baseline column")
    p.add_argument("--fresh", action="store_true", help="start from an empty data dir")
    p.add_argument(
        "--exit",
        "--no-serve",
        dest="exit",
        action="store_true",
        help="stop the service after printing the results (tests, CI)",
    )
    p.set_defaults(func=_run)


# --- 0. the data dir: one demo at a time, reused when the parameters match ------------------------


def _stamp(args: argparse.Namespace) -> dict[str, Any]:
    """What makes the trips: the same stamp gives byte-identical trips (the simulator's fingerprint:
    a hash of ``csr_core/sim``)."""
    from csr_core.bench.runner import simulator_fingerprint

    return {
        "world": args.world,
        "trips": args.trips,
        "trip_length_m": args.trip_length_m,
        "profile": args.profile,
        "seed": args.seed,
        "simulator": simulator_fingerprint(),
    }


def algorithm_fingerprint() -> str:
    """12 hex digits of a hash of the algorithm and the job code (``csr_core`` but the simulator,
    ``workers``): when it changed, a reused data dir holds results of the old code."""
    import hashlib

    root = Path(__file__).resolve().parents[2]
    digest = hashlib.sha1()
    for package in ("csr_core", "workers"):
        for path in sorted((root / package).rglob("*.py")):
            if path.parent.name != "sim":
                digest.update(path.relative_to(root).as_posix().encode() + b"\0" + path.read_bytes())
    return digest.hexdigest()[:12]


@contextlib.contextmanager
def _locked_data_dir(data_dir: Path) -> Iterator[None]:
    """Hold ``DATA_DIR/.lock``: two demos on one SQLite file and one scenario would trip over each other."""
    import fcntl

    data_dir.mkdir(parents=True, exist_ok=True)
    with open(data_dir / ".lock", "w") as lock:
        try:
            fcntl.flock(lock, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            raise SystemExit(
                f"csr demo: another csr demo is running on {data_dir} (use --data-dir)"
            ) from None
        yield


def _prepare_data_dir(data_dir: Path, stamp: dict[str, Any], fresh: bool) -> bool:
    """Empty ``data_dir`` unless it holds a demo of the same ``stamp``; True if it was reused."""
    import orjson

    stamp_path = data_dir / STAMP_FILE
    old = orjson.loads(stamp_path.read_bytes()) if stamp_path.exists() else None
    reused = old == stamp and not fresh
    if not reused:
        if old is not None:
            changed = [k for k in stamp if old.get(k) != stamp[k]]
            why = "--fresh" if fresh else "changed since the last run: " + ", ".join(changed)
            print(f"csr demo: {why}: starting from an empty {data_dir}")
        for child in data_dir.iterdir():
            if child.name == ".lock":
                continue
            if child.name == "service":  # the admin key stays valid (a viewer tab keeps working)
                for part in child.iterdir():
                    if part.name != "admin.key":
                        shutil.rmtree(part) if part.is_dir() else part.unlink()
                continue
            shutil.rmtree(child) if child.is_dir() else child.unlink()
        stamp_path.write_bytes(orjson.dumps(stamp, option=orjson.OPT_INDENT_2))
    return reused


# --- 1. the service ------------------------------------------------------------------------------


def _port_is_free(host: str, port: int) -> bool:
    with socket.socket() as s:
        s.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)  # as uvicorn binds
        try:
            s.bind((host, port))
        except OSError:
            return False
    return True


def choose_port(host: str, wanted: int) -> int:
    """``wanted`` if it can be bound on ``host``, else a free port the system picks."""
    if wanted and _port_is_free(host, wanted):
        return wanted
    with socket.socket() as s:
        s.bind((host, 0))
        return int(s.getsockname()[1])


@dataclass
class Service:
    """A ``csr serve`` subprocess on the embedded default (its own session: Ctrl-C reaches the demo,
    which stops the service in order)."""

    proc: subprocess.Popen
    base_url: str
    admin_key: str
    log_path: Path

    def check_alive(self) -> None:
        if self.proc.poll() is not None:
            raise SystemExit(
                f"csr demo: the service exited ({self.proc.returncode}); its log "
                f"{self.log_path}:\n{_tail(self.log_path)}"
            )

    def stop(self) -> None:
        if self.proc.poll() is None:
            self.proc.send_signal(signal.SIGTERM)
            try:
                self.proc.wait(timeout=30)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait()


def _tail(path: Path, n: int = 20) -> str:
    try:
        return "\n".join(path.read_text(errors="replace").splitlines()[-n:])
    except OSError:
        return "(no log)"


PR_SET_PDEATHSIG = 1  # prctl(2) option: the signal the kernel sends a process when its parent dies


def _stop_with_parent(parent_pid: int) -> Callable[[], None]:
    """A ``preexec_fn``: the child gets SIGTERM when the demo dies, even by SIGKILL (Linux
    ``prctl(PR_SET_PDEATHSIG)``); a demo already gone by then stops it at once. Without it a killed
    demo leaves ``csr serve`` running on its port."""

    def arm() -> None:
        libc = ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6", use_errno=True)
        libc.prctl(PR_SET_PDEATHSIG, signal.SIGTERM)
        if os.getppid() != parent_pid:
            os.kill(os.getpid(), signal.SIGTERM)

    return arm


def start_service(service_dir: Path, host: str, wanted_port: int) -> Service:
    import httpx

    from services.settings import Settings

    service_dir.mkdir(parents=True, exist_ok=True)
    # the admin key, generated into the service's data dir the way `csr serve` does it (and read by it)
    admin_key = Settings(
        data_dir=service_dir, admin_key=None, database_url=None, redis_url=None
    ).admin_secret()
    port = choose_port(host, wanted_port)
    if wanted_port and port != wanted_port:
        print(f"csr demo: port {wanted_port} is taken, using {port}")
    env = {
        k: v
        for k, v in os.environ.items()
        if k not in ("CSR_DATABASE_URL", "CSR_REDIS_URL", "CSR_ADMIN_KEY", "CSR_DATA_DIR")
    }
    env.update(CSR_DATA_DIR=str(service_dir.resolve()), OPENBLAS_NUM_THREADS="1")
    log_path = service_dir / "serve.log"
    csr = Path(sys.executable).parent / "csr"
    argv = (
        [str(csr)]
        if csr.exists()
        else [sys.executable, "-c", "import sys; from services.cli import main; sys.exit(main())"]
    )
    with open(log_path, "ab") as log:
        proc = subprocess.Popen(
            argv + ["serve", "--host", host, "--port", str(port), "--no-access-log"],
            env=env,
            stdout=log,
            stderr=subprocess.STDOUT,
            stdin=subprocess.DEVNULL,
            start_new_session=True,
            preexec_fn=_stop_with_parent(os.getpid()) if sys.platform == "linux" else None,
        )
    url_host = "127.0.0.1" if host in ("0.0.0.0", "::", "") else host
    url_host = f"[{url_host}]" if ":" in url_host else url_host
    base_url = f"http://{url_host}:{port}"
    service = Service(proc, base_url, admin_key, log_path)
    deadline = time.monotonic() + SERVER_START_TIMEOUT_S
    while True:
        service.check_alive()
        with contextlib.suppress(httpx.HTTPError):
            if httpx.get(base_url + "/healthz", timeout=2).status_code == 200:
                return service
        if time.monotonic() > deadline:
            service.stop()
            raise SystemExit(
                f"csr demo: the service did not answer /healthz within {SERVER_START_TIMEOUT_S:.0f} s; "
                f"log {log_path}:\n{_tail(log_path)}"
            )
        time.sleep(0.3)


# --- 2. the fleet --------------------------------------------------------------------------------


def simulate_fleet(args: argparse.Namespace, scenario_dir: Path) -> dict[str, Any]:
    """The scenario of ``args`` (kept from an earlier run of the same parameters: ``scenario.json``
    is written last, so its presence means the folder is complete)."""
    import orjson
    from tqdm import tqdm

    from csr_core.sim import simulate_scenario

    meta_path = scenario_dir / "scenario.json"
    if meta_path.exists():
        return orjson.loads(meta_path.read_bytes())
    with tqdm(total=args.trips, desc=f"simulate {args.world}", unit="trip", file=sys.stderr) as bar:
        return simulate_scenario(
            args.world,
            args.trips,
            args.profile,
            args.seed,
            scenario_dir,
            trip_length_m=args.trip_length_m,
            progress=lambda _trip: bar.update(1),
        )


# --- 3. upload, process, download ----------------------------------------------------------------


class JobProgress:
    """A progress bar over the jobs the upload set off (ingest per trip, then align and merge per tile),
    from ``GET /v1/jobs`` per-queue counts, drawn by a thread while :func:`services.fleet.wait_until_processed`
    decides when everything is done (its own bar counts finished trips, which all finish at the end)."""

    def __init__(self, base_url: str, key: str, poll_s: float = 1.0) -> None:
        import threading

        from services import fleet

        self._http = fleet.client_for(base_url, key, timeout_s=30.0)
        self._poll_s = poll_s
        self._stop = threading.Event()
        self._before = self._finished()  # jobs of earlier runs (a rerun): not this run's work
        self._thread = threading.Thread(target=self._draw, name="demo-progress", daemon=True)

    def _counts(self) -> dict[str, dict[str, int]]:
        return self._http.get("/v1/jobs", params={"limit": 1}).raise_for_status().json()["queues"]

    def _finished(self) -> dict[str, int]:
        return {q: c["done"] + c["failed"] for q, c in self._counts().items()}

    def _draw(self) -> None:
        import httpx
        from tqdm import tqdm

        with tqdm(total=0, desc="process", unit="job", file=sys.stderr) as bar:
            while True:
                stopping = self._stop.is_set()
                with contextlib.suppress(httpx.HTTPError):
                    parts, done, total = [], 0, 0
                    for queue, c in self._counts().items():
                        q_done = c["done"] + c["failed"] - self._before.get(queue, 0)
                        q_total = q_done + c["queued"] + c["running"]
                        done, total = done + q_done, total + q_total
                        if q_total:
                            parts.append(f"{queue} {q_done}/{q_total}")
                    bar.total, bar.n = total, done
                    bar.set_postfix_str(", ".join(parts) or "nothing new to process", refresh=True)
                if stopping or self._stop.wait(self._poll_s):
                    if stopping:
                        return

    def __enter__(self) -> JobProgress:
        self._thread.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self._stop.set()
        self._thread.join(timeout=10)
        self._http.close()


def run_fleet(service: Service, scenario_dir: Path, out_dir: Path) -> dict[str, Any]:
    """Upload (a bar per trip), wait until processed (a bar per job), download the results."""
    from services import fleet

    with fleet.client_for(service.base_url, service.admin_key) as http:
        t0 = time.perf_counter()
        progress = JobProgress(service.base_url, service.admin_key)
        ids = fleet.upload_scenario(http, scenario_dir, progress=True)
        t1 = time.perf_counter()
        with progress:
            statuses = fleet.wait_until_processed(http, ids, timeout_s=PROCESS_TIMEOUT_S, progress=False)
        t2 = time.perf_counter()
        if out_dir.exists():
            shutil.rmtree(out_dir)
        counts = fleet.download_results(http, ids, out_dir, fleet.scenario_bbox(scenario_dir))
        failed, marked = {}, {}
        for key, status in statuses.items():
            trip = http.get(f"/v1/trips/{ids[key]}").json()
            if status == "failed":
                failed[key] = trip.get("error") or "failed"
            quality = trip.get("quality") or {}
            if quality.get("verdict") in ("repaired", "degraded"):
                marked[key] = f"{quality['verdict']}: {quality.get('reason', '')}"
    return {
        "ids": ids,
        "statuses": statuses,
        "failed": failed,
        "marked": marked,
        "counts": counts,
        "upload_s": t1 - t0,
        "process_s": t2 - t1,
    }


def gnss_only_baseline(scenario_dir: Path, out_dir: Path) -> float:
    """``csr reconstruct --method gnss_only`` in-process (kept from an earlier run: the folder is
    renamed into place when complete); its wall seconds (0 when reused)."""
    from csr_core.pipeline import Method, PipelineParams, reconstruct
    from csr_core.scenario import list_trip_files, load_trip, write_reconstruction

    if (out_dir / "report.json").exists():
        return 0.0
    t0 = time.perf_counter()
    trips = [load_trip(f) for f in list_trip_files(scenario_dir)]
    recon = reconstruct(trips, PipelineParams(method=Method.GNSS_ONLY))
    partial = out_dir.with_name(out_dir.name + ".partial")
    if partial.exists():
        shutil.rmtree(partial)
    write_reconstruction(recon, trips, partial, {"method": "gnss_only"})
    partial.rename(out_dir)
    return time.perf_counter() - t0


# --- 4. accuracy table and figures ---------------------------------------------------------------


def _f(value: float, digits: int = 3) -> str:
    return "-" if value is None or (isinstance(value, float) and math.isnan(value)) else f"{value:.{digits}f}"


def accuracy_table(columns: dict[str, Any]) -> str:
    """A compact text table (contract section 6), one column per method (``{name: Evaluation}``)."""
    from csr_core.metrics import TABLE_TYPES

    rows: list[tuple[str, list[str]]] = []

    def row(label: str, fn) -> None:
        rows.append((label, [fn(ev) for ev in columns.values()]))

    row("trips with poses (coverage)", lambda e: f"{e.trips_with_poses}/{e.trips} ({100 * e.coverage:.0f} %)")
    row("ATE RMSE raw / aligned [m]", lambda e: f"{_f(e.raw.ate.rmse)} / {_f(e.aligned.ate.rmse)}")
    row("ATE mean raw / aligned [m]", lambda e: f"{_f(e.raw.ate.mean)} / {_f(e.aligned.ate.mean)}")
    row("RPE RMSE raw / aligned [m]", lambda e: f"{_f(e.raw.rpe.rmse)} / {_f(e.aligned.rpe.rmse)}")
    row("RPE mean raw / aligned [m]", lambda e: f"{_f(e.raw.rpe.mean)} / {_f(e.aligned.rpe.mean)}")
    row("mCD raw / aligned [m]", lambda e: f"{_f(e.map_raw.mcd)} / {_f(e.map_aligned.mcd)}")
    for t in TABLE_TYPES:

        def per_type(e, t=t) -> str:
            s = e.map_aligned.per_type.get(t)
            if s is None or s.n_truth_samples == 0:
                return "no truth"
            return f"{_f(s.cd)} / {_f(100 * s.completeness, 0)} / {_f(100 * s.correctness, 0)}"

        row(f"{t.value}: CD [m] / compl / corr [%]", per_type)
    header = ["aligned unless raw", *columns]
    width = [max(len(header[0]), *(len(r[0]) for r in rows))]
    width += [max(len(name), *(len(r[1][i]) for r in rows)) for i, name in enumerate(columns)]

    def line(cells: list[str]) -> str:
        return "| " + " | ".join(c.ljust(w) for c, w in zip(cells, width, strict=True)) + " |"

    out = [line(header), "|" + "|".join("-" * (w + 2) for w in width) + "|"]
    out += [line([label, *cells]) for label, cells in rows]
    return "\n".join(out)


def write_figures(
    scenario_dir: Path, evaluated: dict[str, Any], meta: dict[str, Any], figures_dir: Path
) -> list[tuple[str, Path]]:
    """The benchmark's figures (:mod:`csr_core.bench.figures`) for the service and the baseline,
    plus a wider map overlay."""
    from csr_core.bench import figures
    from csr_core.bench.runner import CommandRun, Record

    records = [
        Record(
            scenario=meta["name"],
            scenario_dir=scenario_dir,
            world=meta.get("world", ""),
            profile=meta["profile"]["name"] if isinstance(meta.get("profile"), dict) else "",
            method=name,
            variant="",
            run=CommandRun(0, 0.0, 0.0, ""),
            uploaded_bytes=0,
            output_bytes=0,
            km=ev.trip_length_km,
            report={},
            evaluated=ev,
        )
        for name, ev in evaluated.items()
    ]
    out = figures.make_figures(records, figures_dir, "demo")
    wide = figures.plot_map(records, figures_dir / "demo_map_wide.png", half_w=120.0, half_h=75.0)
    return [*out, ("Truth vs reconstruction, a wider window (aligned)", wide)]


# --- the command ---------------------------------------------------------------------------------


def _interrupt(signum: int, frame: object) -> None:
    """SIGTERM (a CI runner, ``kill``) stops the demo like Ctrl-C: the service is stopped in order."""
    raise KeyboardInterrupt


def _run(args: argparse.Namespace) -> int:
    if args.trips < 1 or args.trip_length_m <= 0:
        raise SystemExit("csr demo: --trips must be at least 1 and --trip-length-m positive")
    signal.signal(signal.SIGTERM, _interrupt)
    if not args.verbose:  # the progress bars and the table tell the story; one line per request would bury it
        for noisy in ("httpx", "matplotlib", "csr_core", "services.settings"):
            logging.getLogger(noisy).setLevel(logging.WARNING)
    data_dir: Path = args.data_dir
    started = time.perf_counter()
    with _locked_data_dir(data_dir):
        reused = _prepare_data_dir(data_dir, _stamp(args), args.fresh)
        algorithm_path = data_dir / "algorithm.txt"  # the code that computed the results in data_dir
        if (
            reused
            and algorithm_path.exists()
            and algorithm_path.read_text().strip() != algorithm_fingerprint()
        ):
            print(
                "csr demo: note: the algorithm changed since this data dir was processed; the results below are "
                "the old code's (--fresh recomputes them)"
            )
        service = start_service(data_dir / "service", args.host, args.port)
        shown = False  # the results are printed: Ctrl-C from then on is the normal way out
        try:
            print(
                f"csr demo: service (embedded: SQLite + in-process jobs) on {service.base_url}, "
                f"data in {data_dir}/service" + (" (reused from the last run)" if reused else ""),
                flush=True,
            )
            _demo(args, service, data_dir, started)
            if not algorithm_path.exists():
                algorithm_path.write_text(algorithm_fingerprint() + "\n")
            shown = True
            if args.exit:
                print(
                    f"csr demo: to serve this map again: csr serve --data-dir {data_dir / 'service'}"
                    f" (make serve DATA={data_dir / 'service'})",
                    flush=True,
                )
                return 0
            print("csr demo: serving until Ctrl-C", flush=True)
            while True:
                service.check_alive()
                time.sleep(1.0)
        except KeyboardInterrupt:
            print("\ncsr demo: stopping the service", file=sys.stderr)
            return 0 if shown else 130
        finally:
            service.stop()


def _demo(args: argparse.Namespace, service: Service, data_dir: Path, started: float) -> None:
    """Steps 2-5 against the running ``service``."""
    import httpx
    import orjson

    from csr_core.bench.evaluate import evaluate_output

    scenario_dir = data_dir / "scenario"
    t0 = time.perf_counter()
    meta = simulate_fleet(args, scenario_dir)
    km = sum(t["length_m"] for t in meta["trips"]) / 1000.0
    print(
        f"csr demo: fleet {meta['name']}: {len(meta['trips'])} trips, {km:.1f} km "
        f"({time.perf_counter() - t0:.1f} s) in {scenario_dir}",
        flush=True,
    )

    service.check_alive()
    previous_ids_path = data_dir / "trip_ids.json"
    previous = orjson.loads(previous_ids_path.read_bytes()) if previous_ids_path.exists() else {}
    fleet_run = run_fleet(service, scenario_dir, data_dir / "results" / "service")
    previous_ids_path.write_bytes(orjson.dumps(fleet_run["ids"], option=orjson.OPT_INDENT_2))
    same = sum(previous.get(k) == v for k, v in fleet_run["ids"].items())
    n_aligned = sum(s == "aligned" for s in fleet_run["statuses"].values())
    print(
        f"csr demo: uploaded {len(fleet_run['ids'])} trips in {fleet_run['upload_s']:.1f} s "
        f"({len(fleet_run['ids']) - same} new, {same} already stored under the same ids); processed in "
        f"{fleet_run['process_s']:.1f} s: {n_aligned} aligned, {len(fleet_run['failed'])} failed; "
        f"{fleet_run['counts']['features']} map features",
        flush=True,
    )
    for key, error in fleet_run["failed"].items():
        print(f"  failed {key}: {error}")
    for key, verdict in fleet_run["marked"].items():  # poses off the trip's own GNSS at first
        print(f"  {key}: {verdict}")

    evaluated = {SERVICE_METHOD: evaluate_output(scenario_dir, data_dir / "results" / "service")}
    if not args.no_baseline:
        seconds = gnss_only_baseline(scenario_dir, data_dir / "results" / "gnss_only")
        evaluated["GNSS-only"] = evaluate_output(scenario_dir, data_dir / "results" / "gnss_only")
        if seconds:
            print(
                f"csr demo: GNSS-only baseline (csr reconstruct --method gnss_only) in {seconds:.1f} s",
                flush=True,
            )
    table = accuracy_table({name: ev.evaluation for name, ev in evaluated.items()})
    title = (
        f"Accuracy against ground truth: {meta['name']}, {len(meta['trips'])} trips, {km:.1f} km "
        f"(contract section 6; aligned = after one global SE(2) fit)"
    )
    print(f"\n{title}\n\n{table}\n", flush=True)
    (data_dir / "accuracy.md").write_text(f"{title}\n\n{table}\n")
    (data_dir / "accuracy.json").write_bytes(
        orjson.dumps(
            {name: ev.evaluation.as_dict() for name, ev in evaluated.items()},
            option=orjson.OPT_INDENT_2 | orjson.OPT_SERIALIZE_NUMPY,
        )
    )

    figures = write_figures(scenario_dir, evaluated, meta, data_dir / "figures")
    print("csr demo: figures")
    for caption, path in figures:
        print(f"  {path}  {caption}")

    service.check_alive()
    print(f"\ncsr demo: done in {time.perf_counter() - started:.0f} s")
    for label, route in (("viewer", "/viewer/"), ("ops", "/ops/"), ("API docs", "/docs")):
        answer = httpx.get(service.base_url + route, timeout=10)
        note = "" if answer.status_code == 200 else f"   (answers {answer.status_code}: {answer.text[:120]})"
        print(f"  {label:<11} {service.base_url}{route}{note}")
    print(
        f"  {'admin key':<11} {service.admin_key}   (also in {data_dir}/service/admin.key; the pages ask for it)\n"
        f"  {'service log':<11} {service.log_path}",
        flush=True,
    )
