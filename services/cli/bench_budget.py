"""`csr bench-budget [--set standard-seeds] [--out bench-out] [--jobs 2] [--write BENCHMARKS.md]`:
where issue 6's mCD comes from (``csr_core.bench.error_budget``).

Simulates (or reuses from ``--out``/scenarios) the set's scenarios and fuses each one's trips on
the pipeline's poses, on the poses of an alignment whose registrations are exact, and on the
true poses (single-trip results cached in ``--out``/budget); prints the section, draws the bars
into ``--figures`` and, with ``--write``, rewrites the set's section of the markdown (``error-budget``
for ``standard-seeds``, ``error-budget-SET`` for the others).
"""

from __future__ import annotations

import argparse
import logging
import sys
import time
from pathlib import Path


def register(sub: argparse._SubParsersAction) -> None:
    from csr_core.bench.sets import SCENARIO_SETS

    p = sub.add_parser("bench-budget", help="issue 6's mCD split into what the poses and the element stages leave")
    p.add_argument("--set", dest="set_name", default="standard-seeds", choices=SCENARIO_SETS,
                   help="scenario set (default standard-seeds: issue 6's standard profile)")
    p.add_argument("--out", default="bench-out", help="work folder: scenarios cache and budget/ (single-trip results)")
    p.add_argument("--jobs", type=int, default=2, help="scenarios evaluated in parallel (processes; default 2)")
    p.add_argument("--write", metavar="MARKDOWN", help="rewrite the error-budget section of this file")
    p.add_argument("--figures", default="docs/figures", help="where the PNG figure goes")
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
    from csr_core.bench.tables import write_section
    from csr_core.errors import CsrError

    for name in ("csr_core.single_trip", "csr_core.alignment", "csr_core.topology"):
        logging.getLogger(name).setLevel(logging.WARNING)  # lines per trip and stage otherwise
    t0 = time.perf_counter()
    out_root = Path(args.out)
    try:
        results = run_budget_bench(
            out_root / "scenarios", out_root / "budget", args.set_name, jobs=args.jobs,
            progress=lambda msg: print(f"[{time.perf_counter() - t0:6.0f} s] {msg}", file=sys.stderr),
        )
    except CsrError as exc:
        print(f"csr bench-budget: {exc}", file=sys.stderr)
        return 2
    elapsed = time.perf_counter() - t0
    (out_root / "budget" / f"results-{args.set_name}.json").write_bytes(orjson.dumps(results, option=orjson.OPT_INDENT_2))
    figure = plot_budget(results, Path(args.figures) / figure_name(args.set_name), args.set_name)
    doc = Path(args.write) if args.write else None
    section = render_section(results, figure, doc.parent if doc else Path("."), elapsed, args.set_name)
    print(section)
    if doc is not None:
        write_section(doc, section, section_name(args.set_name))
        print(f"csr bench-budget: wrote the {section_name(args.set_name)} section of {doc}", file=sys.stderr)
    return 0
