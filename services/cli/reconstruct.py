"""`csr reconstruct SCENARIO_DIR --out OUT_DIR [--method ...]` (contract section 4).

Runs the whole reconstruction in one process on ``SCENARIO_DIR/trips/`` (file-name order, as if
uploaded in that order; never ``truth/``) and writes ``OUT_DIR/poses/<key>.csv``,
``OUT_DIR/map.geojson``, ``OUT_DIR/held_back.geojson`` (lines kept out of the map for a human to
look at) and ``OUT_DIR/report.json`` (failures, timings). Exit code 2 with a
message naming the file for a missing or invalid scenario.
"""

from __future__ import annotations

import argparse
import sys
import time


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "reconstruct", help="reconstruct poses and map of a scenario folder's trips (no server)"
    )
    p.add_argument(
        "scenario_dir",
        metavar="SCENARIO_DIR",
        help="scenario folder (contract section 5); only trips/ is read",
    )
    p.add_argument("--out", required=True, metavar="OUT_DIR", help="output folder (poses/*.csv, map.geojson)")
    p.add_argument(
        "--method",
        choices=("pipeline", "gnss_only", "roadmap_icp"),
        default="pipeline",
        help="the project's pipeline (default) or a benchmark baseline",
    )
    p.add_argument("--no-coarse", action="store_true", help="pipeline without coarse alignment (ablation)")
    p.add_argument("--no-fine", action="store_true", help="pipeline without fine alignment (ablation)")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")
    p.set_defaults(func=_run)


def _run(args: argparse.Namespace) -> int:
    from tqdm import tqdm

    from csr_core.errors import CsrError, ScenarioError
    from csr_core.pipeline import Method, PipelineParams, reconstruct
    from csr_core.scenario import list_trip_files, load_trip, write_reconstruction

    t_start = time.perf_counter()
    try:
        files = list_trip_files(args.scenario_dir)
        trips = [
            load_trip(f)
            for f in tqdm(files, desc="load trips", unit="trip", file=sys.stderr, disable=args.no_progress)
        ]
    except ScenarioError as exc:
        print(f"csr reconstruct: {exc}", file=sys.stderr)
        return 2
    t_loaded = time.perf_counter()
    params = PipelineParams(method=Method(args.method), coarse=not args.no_coarse, fine=not args.no_fine)
    try:
        recon = reconstruct(trips, params)
    except CsrError as exc:
        print(f"csr reconstruct: reconstruction failed: {exc}", file=sys.stderr)
        return 1
    t_done = time.perf_counter()
    uploaded_bytes = sum(f.n_bytes for f in files)
    frames = sum(t.n_frames for t in trips)
    report = {
        "method": params.method.value,
        "params": {"coarse": params.coarse, "fine": params.fine},
        "uploaded_bytes": uploaded_bytes,
        "frames": frames,
        "timings_s": {"load": t_loaded - t_start, "reconstruct": t_done - t_loaded},
    }
    out = write_reconstruction(recon, trips, args.out, report)
    t_end = time.perf_counter()
    # Rewrite the report with the write time included (cheap; the file is small).
    import orjson

    report_path = out / "report.json"
    full = orjson.loads(report_path.read_bytes())
    full["timings_s"]["write"] = t_end - t_done
    full["timings_s"]["total"] = t_end - t_start
    report_path.write_bytes(orjson.dumps(full, option=orjson.OPT_INDENT_2))
    print(
        f"csr reconstruct: {params.method.value}: {len(trips)} trips ({frames} frames, "
        f"{uploaded_bytes / 1e6:.1f} MB uploaded), {len(trips) - len(recon.failed)} with poses, "
        f"{len(recon.failed)} failed, {len(recon.map_features)} map features "
        f"({len(recon.held_back_features)} lines held back), {t_end - t_start:.1f} s -> {out}"
    )
    return 0
