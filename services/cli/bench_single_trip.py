"""`csr bench-single-trip [--out bench-out] [--jobs 2] [--write BENCHMARKS.md]`: the
targets (single-trip reconstruction, paper III-C) on the benchmark's fleets.

Simulates (or reuses from ``--out``/scenarios) the ``standard-seeds`` and ``hard`` sets, runs the
single-trip stage on every trip alone and scores it against the truth
(``csr_core.bench.single_trip``), prints the tables, draws the figure into ``--figures`` and,
with ``--write``, rewrites the ``single-trip`` section of the markdown file (between
``<!-- bench:single-trip:begin -->`` and ``<!-- bench:single-trip:end -->``).
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

from services.cli.bench_common import (
    add_output_arguments,
    doc_dir,
    progress_printer,
    publish,
    quiet_stage_logs,
)


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("bench-single-trip", help="the single-trip targets on the benchmark's fleets")
    p.add_argument(
        "--sets",
        default="standard-seeds,hard",
        help="comma-separated scenario sets (default standard-seeds,hard; hard gives the GNSS-jump rows)",
    )
    add_output_arguments(
        p,
        "work folder: scenarios cache and single-trip/results.json",
        "rewrite the single-trip section of this file",
    )
    p.set_defaults(func=_run)


def _run(args: argparse.Namespace) -> int:
    import orjson

    from csr_core.bench.sets import SCENARIO_SETS
    from csr_core.bench.single_trip import (
        SECTION,
        plot_instances_by_world,
        render_section,
        run_single_trip_bench,
    )
    from csr_core.errors import CsrError

    sets = [s.strip() for s in args.sets.split(",") if s.strip()]
    unknown = [s for s in sets if s not in SCENARIO_SETS]
    if unknown or not sets:
        print(
            f"csr bench-single-trip: unknown set(s) {unknown or sets} (known: {', '.join(SCENARIO_SETS)})",
            file=sys.stderr,
        )
        return 2
    quiet_stage_logs(("csr_core.single_trip",))  # one line per trip otherwise
    t0 = time.perf_counter()
    out_root = Path(args.out)
    try:
        results = run_single_trip_bench(
            out_root / "scenarios",
            sets=sets,
            jobs=args.jobs,
            progress=progress_printer(t0),
        )
    except CsrError as exc:
        print(f"csr bench-single-trip: {exc}", file=sys.stderr)
        return 2
    elapsed = time.perf_counter() - t0
    (out_root / "single-trip").mkdir(parents=True, exist_ok=True)
    (out_root / "single-trip" / "results.json").write_bytes(
        orjson.dumps(results, option=orjson.OPT_INDENT_2 | orjson.OPT_SERIALIZE_NUMPY)
    )
    figure = plot_instances_by_world(results, Path(args.figures) / "bench_single_trip_instances.png")
    section = render_section(results, figure, doc_dir(args.write), elapsed, sets)
    publish(section, args.write, SECTION, "bench-single-trip")
    return 0
