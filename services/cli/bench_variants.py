"""`csr bench-variants [--set variants] [--variants a,b] [--out bench-out] [--jobs 2] [--write BENCHMARKS.md]`:
the pipeline on foreign fleets, contract-valid uploads our simulator never writes.

Simulates (or reuses from ``--out``/scenarios) the set's fleets, rewrites each into every variant
of ``csr_core.bench.variants`` (``--out``/variants), runs ``csr reconstruct`` on each and scores it
against the fleet's truth; prints the section and, with ``--write``, rewrites the ``variants``
section of the markdown file. Exit status 1 when a variant fails to run.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

from services.cli.bench_common import add_output_arguments, doc_dir, progress_printer, publish


def register(sub: argparse._SubParsersAction) -> None:
    from csr_core.bench.sets import SCENARIO_SETS
    from csr_core.bench.variants import VARIANTS

    p = sub.add_parser("bench-variants", help="the pipeline on contract-valid fleets unlike the simulator's")
    p.add_argument(
        "--set",
        dest="set_name",
        default="variants",
        choices=SCENARIO_SETS,
        help="the source fleets (default variants: urban and roundabout, 6 trips x 800 m)",
    )
    p.add_argument(
        "--variants", default="", help=f"comma-separated subset of: {', '.join(VARIANTS)} (default all)"
    )
    add_output_arguments(
        p,
        "work folder: scenarios cache and variants/",
        "rewrite the variants section of this file",
        jobs_help="runs in parallel (processes; default 2)",
    )
    p.set_defaults(func=_run)


def _run(args: argparse.Namespace) -> int:
    from csr_core.bench.runner import ensure_scenario, simulator_fingerprint
    from csr_core.bench.sets import scenario_set
    from csr_core.bench.variants import SECTION, plot_variants, render_section, run_variants_bench

    t0 = time.perf_counter()
    out_root = Path(args.out)

    progress = progress_printer(t0)

    fingerprint = simulator_fingerprint()
    sources = {}
    for spec in scenario_set(args.set_name):
        progress(f"scenario {spec.name}")
        sources[spec.name] = ensure_scenario(spec, out_root / "scenarios", fingerprint)
    names = [n.strip() for n in args.variants.split(",") if n.strip()] or None
    try:
        rows = run_variants_bench(sources, out_root / "variants", names, jobs=args.jobs, progress=progress)
    except ValueError as exc:
        print(f"csr bench-variants: {exc}", file=sys.stderr)
        return 2
    import orjson

    (out_root / "variants" / "results.json").write_bytes(orjson.dumps(rows, option=orjson.OPT_INDENT_2))
    regenerate = "csr bench-variants --write BENCHMARKS.md" + (
        "" if args.set_name == "variants" else f" --set {args.set_name}"
    )
    figure = plot_variants(rows, Path(args.figures) / "bench_variants.png")
    section = render_section(rows, time.perf_counter() - t0, regenerate, figure, doc_dir(args.write))
    publish(section, args.write, SECTION, "bench-variants")
    failed = [f"{r['base']} {r['variant']}" for r in rows if not r["ok"]]
    if failed:
        print(f"csr bench-variants: failed to run: {', '.join(failed)}", file=sys.stderr)
        return 1
    return 0
