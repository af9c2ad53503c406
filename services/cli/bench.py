"""`csr bench [--set quick|standard|standard-seeds|dense|hard|full|toy] [--out bench-out] [--write BENCHMARKS.md]`.

Simulates the set's scenarios (cached), runs `csr reconstruct` with the pipeline and both
baselines, evaluates per contract section 6, prints the tables, writes figures to
``--figures`` (default ``docs/figures``) and, with ``--write``, rewrites only the bench section
of the given markdown file that belongs to the set (between ``<!-- bench:SET:begin -->`` and
``<!-- bench:SET:end -->``; other sets' sections are left as they are).
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("bench", help="benchmark the pipeline and baselines on simulated scenarios")
    from csr_core.bench.sets import SCENARIO_SETS

    p.add_argument(
        "--set",
        dest="set_name",
        default="quick",
        choices=SCENARIO_SETS,
        help="standard: the five worlds, 10 trips x 1.5 km, seed 1; standard-seeds: the same at seeds 1-3; "
        "dense: 20-70 trips per world, >= 10 trips per place (the targets' condition)",
    )
    p.add_argument("--out", default="bench-out", help="work folder: scenarios cache, runs, results.json")
    p.add_argument(
        "--write", metavar="MARKDOWN", help="rewrite the bench section of this file (e.g. BENCHMARKS.md)"
    )
    p.add_argument("--figures", default="docs/figures", help="where the PNG figures go")
    p.add_argument(
        "--reuse-runs",
        action="store_true",
        help="re-evaluate earlier successful runs found in --out instead of re-running them",
    )
    p.add_argument("--methods", default="pipeline,gnss_only,roadmap_icp", help="comma-separated methods")
    p.add_argument(
        "--no-ablation",
        dest="ablation",
        action="store_false",
        help="skip the coarse-only and fine-only runs of the pipeline (Table I)",
    )
    p.set_defaults(func=_run)


def _run(args: argparse.Namespace) -> int:
    import orjson

    from csr_core.bench.figures import make_figures, plot_ate_by_density
    from csr_core.bench.report import render_section
    from csr_core.bench.runner import run_bench
    from csr_core.bench.tables import table_cost, table_map, table_pose, write_section
    from csr_core.errors import CsrError

    t0 = time.perf_counter()
    out_root = Path(args.out)
    out_root.mkdir(parents=True, exist_ok=True)
    methods = [m.strip() for m in args.methods.split(",") if m.strip()]
    try:
        records = run_bench(
            args.set_name,
            out_root,
            methods,
            ablation=args.ablation,
            progress=lambda msg: print(f"[{time.perf_counter() - t0:6.0f} s] {msg}", file=sys.stderr),
            reuse=args.reuse_runs,
        )
    except CsrError as exc:
        print(f"csr bench: {exc}", file=sys.stderr)
        return 2
    elapsed = time.perf_counter() - t0
    results = [
        {
            "scenario": r.scenario,
            "method": r.method,
            "variant": r.variant,
            "returncode": r.run.returncode,
            "wall_s": r.run.wall_s,
            "peak_rss_mb": r.run.peak_rss_mb,
            "uploaded_bytes": r.uploaded_bytes,
            "output_bytes": r.output_bytes,
            "km": r.km,
            "evaluation": r.evaluated.evaluation.as_dict() if r.evaluated else None,
        }
        for r in records
    ]
    (out_root / "results.json").write_bytes(
        orjson.dumps(results, option=orjson.OPT_INDENT_2 | orjson.OPT_SERIALIZE_NUMPY)
    )
    figures = []
    first = records[0].scenario if records else None
    fig_records = [r for r in records if r.scenario == first and not r.variant and r.ok]
    if fig_records:
        figures = make_figures(fig_records, Path(args.figures), f"bench_{args.set_name}")
    density = plot_ate_by_density(records, Path(args.figures) / f"bench_{args.set_name}_ate_by_density.png")
    if density is not None:
        figures.append(("Aligned pose error against fleet density (trips per place)", density))
    print(table_map(records), table_pose(records), table_cost(records), sep="\n\n")
    if args.write:
        doc = Path(args.write)
        run_s = sum(r.run.wall_s for r in records)
        write_section(
            doc, render_section(records, args.set_name, figures, doc.parent, elapsed, run_s), args.set_name
        )
        print(f"csr bench: wrote the bench section of {doc}", file=sys.stderr)
    failed = [r for r in records if not r.ok]
    print(f"csr bench: {len(records)} runs on set {args.set_name!r}, {len(failed)} failed, {elapsed:.0f} s")
    return 1 if failed else 0
