"""`csr bench-lanelet2 [--worlds ...] [--trips 4] [--seed 1] [--out bench-out/lanelet2]
[--write BENCHMARKS.md]`: the Lanelet2 export of each benchmark world's truth map and of the
pipeline's map of a small simulated fleet, judged by Lanelet2's validator checks and routing
graph (``csr_core.bench.lanelet2``); prints the section and, with ``--write``, rewrites the
``lanelet2`` section of the markdown file.
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

from services.cli.bench_common import progress_printer, publish, quiet_stage_logs


def register(sub: argparse._SubParsersAction) -> None:
    from csr_core.bench.lanelet2 import WORLDS

    p = sub.add_parser(
        "bench-lanelet2", help="the Lanelet2 export of truth and pipeline maps, checked and routed"
    )
    p.add_argument("--worlds", nargs="+", default=list(WORLDS), choices=WORLDS, metavar="WORLD")
    p.add_argument("--trips", type=int, default=4, help="simulated trips per world (default 4)")
    p.add_argument("--seed", type=int, default=1)
    p.add_argument(
        "--out", default="bench-out/lanelet2", help="work folder: OUT/<world> scenarios, OUT/<world>/rec"
    )
    p.add_argument("--write", metavar="MARKDOWN", help="rewrite the lanelet2 section of this file")
    p.set_defaults(func=_run)


def _run(args: argparse.Namespace) -> int:
    from csr_core.bench.lanelet2 import lanelet2_row, lanelet2_table, pipeline_map, truth_map

    quiet_stage_logs(("csr_core.single_trip", "csr_core.alignment", "csr_core.topology", "csr_core.export"))
    t0 = time.perf_counter()
    say = progress_printer(t0)
    rows = []
    for world in args.worlds:
        rows.append(lanelet2_row(world, "truth", truth_map(world)))
        say(f"{world}: truth checked")
        rows.append(
            lanelet2_row(world, "pipeline", pipeline_map(world, Path(args.out), args.trips, args.seed))
        )
        say(f"{world}: pipeline map ({args.trips} trips) checked")
    command = f"csr bench-lanelet2 --trips {args.trips} --seed {args.seed}"
    section = "\n".join(
        [
            f"## Lanelet2 export (`{command}`)",
            "",
            "Per world, the Lanelet2 export (`csr export`) of the truth map and of the pipeline's map of "
            f"{args.trips} simulated trips (seed {args.seed}, standard profile), loaded with the `lanelet2` "
            "package and judged by Lanelet2's validator checks (`csr export --validate`, "
            "`csr_core/export/lanelet2_checks.py`). Routing with German vehicle rules: the share of "
            "ordered pairs of road lanelets with a route (from every road lanelet to every other) and the largest strongly connected component of the routable relations "
            "(following, lane changes).",
            "",
            lanelet2_table(rows),
            "",
            f"Regenerate: `{command} --write BENCHMARKS.md` ({time.perf_counter() - t0:.0f} s with the fleets "
            "already simulated and reconstructed in `--out`; each fleet's `csr simulate` and `csr reconstruct` "
            "add a few minutes). Errors count `io.load`, `mapping.duplicated_points` and "
            "`routing_graph.routing_graph_is_valid`; most warnings are `mapping.curvature_too_big`.",
        ]
    )
    publish(section, args.write, "lanelet2", "bench-lanelet2")
    return 0
