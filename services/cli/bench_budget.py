"""`csr bench-budget [--set standard-seeds] [--out bench-out] [--jobs 2] [--write BENCHMARKS.md]`:
where the map's mCD comes from (``csr_core.bench.error_budget``).

Simulates (or reuses from ``--out``/scenarios) the set's scenarios and fuses each one's trips on
the pipeline's poses, on the poses of an alignment whose registrations are exact, and on the
true poses (single-trip results cached in ``--out``/budget); prints the section, draws the bars
into ``--figures`` and, with ``--write``, rewrites the set's section of the markdown (``error-budget``
for ``standard-seeds``, ``error-budget-SET`` for the others).
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
    from csr_core.bench.sets import SCENARIO_SETS

    p = sub.add_parser("bench-budget", help="the mCD split into what the poses and the element stages leave")
    p.add_argument(
        "--set",
        dest="set_name",
        default="standard-seeds",
        choices=SCENARIO_SETS,
        help="scenario set (default standard-seeds: the standard profile)",
    )
    add_output_arguments(
        p,
        "work folder: scenarios cache and budget/ (single-trip results)",
        "rewrite the set's error-budget section of this file",
    )
    p.set_defaults(func=_run)


def _run(args: argparse.Namespace) -> int:
    import orjson

    from csr_core.bench.error_budget import (
        figure_name,
        plot_budget,
        render_section,
        run_budget_bench,
        section_name,
    )
    from csr_core.errors import CsrError

    quiet_stage_logs()
    t0 = time.perf_counter()
    out_root = Path(args.out)
    try:
        results = run_budget_bench(
            out_root / "scenarios",
            out_root / "budget",
            args.set_name,
            jobs=args.jobs,
            progress=progress_printer(t0),
        )
    except CsrError as exc:
        print(f"csr bench-budget: {exc}", file=sys.stderr)
        return 2
    elapsed = time.perf_counter() - t0
    (out_root / "budget" / f"results-{args.set_name}.json").write_bytes(
        orjson.dumps(results, option=orjson.OPT_INDENT_2)
    )
    figure = plot_budget(results, Path(args.figures) / figure_name(args.set_name), args.set_name)
    section = render_section(results, figure, doc_dir(args.write), elapsed, args.set_name)
    publish(section, args.write, section_name(args.set_name), "bench-budget")
    return 0
