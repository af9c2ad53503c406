"""`csr bench-upload-size SCENARIO_DIR [--reconstruct N]`: upload bytes per km of the JSON and
the compact binary upload over a scenario's trips, and the single-trip reconstruction from each
binary variant against the JSON's (``csr_core.bench.upload_size``). Prints a Markdown table."""

from __future__ import annotations

import argparse
from pathlib import Path


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("bench-upload-size", help="bytes per km of the JSON and the compact binary upload")
    p.add_argument("scenario", type=Path, help="a scenario folder (csr simulate)")
    p.add_argument(
        "--reconstruct", type=int, default=2, metavar="N", help="compare reconstructions on the first N trips"
    )
    p.set_defaults(func=_run)


def _run(args: argparse.Namespace) -> int:
    from csr_core.bench.upload_size import markdown, measure

    sizes, reconstructions = measure(args.scenario, n_reconstruct=args.reconstruct)
    print(markdown(sizes, reconstructions))
    return 0
