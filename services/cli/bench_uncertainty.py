"""`csr bench-uncertainty [--worlds ...] [--trips 6] [--trip-length-m 600] [--seeds 1 ...]
[--out bench-out/uncertainty] [--write BENCHMARKS.md]`: the calibration of the map's absolute
uncertainty (``csr_core.bench.uncertainty``) on simulated fleets of the real-map worlds; prints the
section and, with ``--write``, rewrites the ``uncertainty`` section of the markdown file.
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

from services.cli.bench_common import progress_printer, publish


def register(sub: argparse._SubParsersAction) -> None:
    from csr_core.bench.sets import REAL_MAP_WORLDS

    p = sub.add_parser(
        "bench-uncertainty", help="2 sigma_abs coverage of raw errors and the certificate's error"
    )
    p.add_argument("--worlds", nargs="+", default=list(REAL_MAP_WORLDS), metavar="WORLD")
    p.add_argument("--trips", type=int, default=6, help="simulated trips per world (default 6)")
    p.add_argument("--trip-length-m", type=float, default=600.0, help="length of each trip (default 600 m)")
    p.add_argument("--seeds", type=int, nargs="+", default=[1], help="fleet seeds (default 1)")
    p.add_argument(
        "--out", default="bench-out/uncertainty", help="work folder: scenarios and reconstructions"
    )
    p.add_argument("--write", metavar="MARKDOWN", help="rewrite the uncertainty section of this file")
    p.set_defaults(func=_run)


def _run(args: argparse.Namespace) -> int:
    from csr_core.bench.runner import csr_command, ensure_scenario, run_measured
    from csr_core.bench.sets import ScenarioSpec
    from csr_core.bench.uncertainty import calibration_row, calibration_table, scenario_errors
    from csr_core.errors import CsrError

    t0 = time.perf_counter()
    say = progress_printer(t0)
    out = Path(args.out)
    rows, pooled = [], []
    for world in args.worlds:
        for seed in args.seeds:
            spec = ScenarioSpec(world, args.trips, "standard", seed, args.trip_length_m)
            scenario = ensure_scenario(spec, out / "scenarios")
            rec = out / "reconstructions" / scenario.name
            if not (rec / "map.geojson").exists():
                run = run_measured(
                    [*csr_command(), "reconstruct", str(scenario), "--out", str(rec), "--no-progress"]
                )
                if run.returncode != 0:
                    raise CsrError(f"csr reconstruct failed for {spec.name}: {run.stderr_tail}")
            errors, unmatched, trips = scenario_errors(scenario, rec)
            rows.append(calibration_row(spec.name, errors, unmatched, trips))
            pooled.append((errors, unmatched, trips))
            say(f"{spec.name}: calibrated")
    if len(rows) > 1:
        rows.append(
            calibration_row(
                "all scenarios",
                [e for errors, _, _ in pooled for e in errors],
                sum(u for _, u, _ in pooled),
                sum(t for _, _, t in pooled),
            )
        )
    command = (
        f"csr bench-uncertainty --worlds {' '.join(args.worlds)} --trips {args.trips} "
        f"--trip-length-m {args.trip_length_m:g} --seeds {' '.join(map(str, args.seeds))}"
    )
    section = "\n".join(
        [
            f"## Absolute uncertainty (`{command}`)",
            "",
            "Per world, the pipeline's map of a simulated fleet (standard profile) against the truth with no "
            "alignment of map to truth (`csr_core/bench/uncertainty.py`): the share of elements whose raw lateral "
            "error (median distance to the nearest truth element of the type) is within 2 `sigma_abs_m` "
            "(Gaussian: 95 %) and within 2 `uncertainty_m` (the relative sigma), and the certificate's expected "
            "absolute error (length-weighted RMS of `sigma_abs_m`) against the measured length-weighted RMS raw "
            "error. `false`: elements farther than 3 m from every truth element of their type (not counted).",
            "",
            calibration_table(rows),
            "",
            f"Regenerate: `{command} --write BENCHMARKS.md` ({time.perf_counter() - t0:.0f} s here, simulation and "
            "reconstruction included unless cached in `--out`).",
        ]
    )
    publish(section, args.write, "uncertainty", "bench-uncertainty")
    return 0
