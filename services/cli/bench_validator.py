"""`csr bench-validator [--set validator] [--out bench-out] [--jobs 2] [--write BENCHMARKS.md]`:
issue 6's validator target (recall >= 0.8 at precision >= 0.5 on the hard profile).

Simulates (or reuses from ``--out``/scenarios) the set's fleets, aligns them (cached in
``--out``/validator), generates the topology as the pipeline does and judges every instance
against the truth (``csr_core.bench.validator``); prints the section, draws one fleet's map into
``--figures`` and, with ``--write``, rewrites the ``validator`` section of the markdown file.
"""

from __future__ import annotations

import argparse
import logging
import sys
import time
from pathlib import Path


def register(sub: argparse._SubParsersAction) -> None:
    from csr_core.bench.sets import SCENARIO_SETS

    p = sub.add_parser("bench-validator", help="issue 6's validator recall / precision on the hard profile")
    p.add_argument("--set", dest="set_name", default="validator", choices=SCENARIO_SETS,
                   help="scenario set (default validator: six hard fleets of 8 trips)")
    p.add_argument("--out", default="bench-out", help="work folder: scenarios cache and validator/ (alignments)")
    p.add_argument("--jobs", type=int, default=2, help="fleets evaluated in parallel (processes; default 2)")
    p.add_argument("--write", metavar="MARKDOWN", help="rewrite the validator section of this file")
    p.add_argument("--figures", default="docs/figures", help="where the PNG figure goes")
    p.set_defaults(func=_run)


def _run(args: argparse.Namespace) -> int:
    import orjson

    from csr_core.bench.tables import write_section
    from csr_core.bench.validator import SECTION, render_section, run_validator_bench
    from csr_core.errors import CsrError

    for name in ("csr_core.single_trip", "csr_core.alignment", "csr_core.topology"):
        logging.getLogger(name).setLevel(logging.WARNING)  # lines per trip and stage otherwise
    t0 = time.perf_counter()
    out_root = Path(args.out)
    figure_dir = Path(args.figures)
    try:
        results = run_validator_bench(
            out_root / "scenarios", out_root / "validator", args.set_name, jobs=args.jobs,
            figure_dir=figure_dir,
            progress=lambda msg: print(f"[{time.perf_counter() - t0:6.0f} s] {msg}", file=sys.stderr),
        )
    except CsrError as exc:
        print(f"csr bench-validator: {exc}", file=sys.stderr)
        return 2
    elapsed = time.perf_counter() - t0
    (out_root / "validator" / "results.json").write_bytes(orjson.dumps(results, option=orjson.OPT_INDENT_2))
    figure = next((Path(r["figure"]) for r in results if r["figure"]), None)
    doc = Path(args.write) if args.write else None
    section = render_section(results, figure, doc.parent if doc else Path("."), elapsed, args.set_name)
    print(section)
    if doc is not None:
        write_section(doc, section, SECTION)
        print(f"csr bench-validator: wrote the {SECTION} section of {doc}", file=sys.stderr)
    return 0
