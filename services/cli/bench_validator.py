"""`csr bench-validator [--set validator] [--out bench-out] [--jobs 2] [--write BENCHMARKS.md]`:
the validator target (recall >= 0.8 at precision >= 0.5 on the hard profile).

Simulates (or reuses from ``--out``/scenarios) the set's fleets, aligns them (cached in
``--out``/validator), generates the topology as the pipeline does and judges every instance
against the truth (``csr_core.bench.validator``); prints the section, draws one fleet's map and
what a validator can reach there into ``--figures`` and, with ``--write``, rewrites the ``validator`` section of the markdown file.
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

    p = sub.add_parser("bench-validator", help="the validator's recall / precision on the hard profile")
    p.add_argument(
        "--set",
        dest="set_name",
        default="validator",
        choices=SCENARIO_SETS,
        help="scenario set (default validator: six hard fleets of 8 trips)",
    )
    add_output_arguments(
        p,
        "work folder: scenarios cache and validator/ (alignments)",
        "rewrite the validator section of this file",
        jobs_help="fleets evaluated in parallel (processes; default 2)",
    )
    p.set_defaults(func=_run)


def _run(args: argparse.Namespace) -> int:
    import orjson

    from csr_core.bench.validator import SECTION, render_section, run_validator_bench
    from csr_core.errors import CsrError

    quiet_stage_logs()
    t0 = time.perf_counter()
    out_root = Path(args.out)
    figure_dir = Path(args.figures)
    try:
        results = run_validator_bench(
            out_root / "scenarios",
            out_root / "validator",
            args.set_name,
            jobs=args.jobs,
            figure_dir=figure_dir,
            progress=progress_printer(t0),
        )
    except CsrError as exc:
        print(f"csr bench-validator: {exc}", file=sys.stderr)
        return 2
    elapsed = time.perf_counter() - t0
    (out_root / "validator" / "results.json").write_bytes(orjson.dumps(results, option=orjson.OPT_INDENT_2))
    figure = next((Path(r["figure"]) for r in results if r["figure"]), None)
    section = render_section(
        results,
        figure,
        doc_dir(args.write),
        elapsed,
        args.set_name,
        reach_figure=figure_dir / "bench_validator_reach.png",
    )
    publish(section, args.write, SECTION, "bench-validator")
    return 0
