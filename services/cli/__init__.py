"""The ``csr`` command (contract section 4). Each subcommand lives in its own module here and
exposes ``register(subparsers)``; heavy imports happen inside the command, not at start."""

from __future__ import annotations

import os

# One BLAS thread per process, before numpy is first imported: on small matrices (RRWM affinity,
# gtsam) OpenBLAS's thread hand-off made timings erratic and slower on 2 cores
# (shared/LIBRARY-NOTES.md, pygmtools). Parallelism comes from processes (workers, trips).
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import argparse  # noqa: E402
import importlib  # noqa: E402
import logging  # noqa: E402
import sys  # noqa: E402

# module name -> owns these subcommands
_COMMAND_MODULES: tuple[str, ...]
_COMMAND_MODULES = ("serve", "worker", "simulate", "reconstruct", "bench", "bench_ingest", "reprocess")
_COMMAND_MODULES += ("export",)  # csr export: Lanelet2 (services/cli/export.py)
_COMMAND_MODULES += ("bench_service",)  # csr bench-service: the per-tile pipeline over HTTP
_COMMAND_MODULES += ("bench_tiles",)  # csr bench-tiles: tile serving vs nginx (services/cli/bench_tiles.py)
_COMMAND_MODULES += ("bench_match_pairs",)  # csr bench-match-pairs: a tile's match-pairs listing
_COMMAND_MODULES += ("demo",)  # csr demo: the README's first command (services/cli/demo.py)
_COMMAND_MODULES += ("bench_single_trip",)  # csr bench-single-trip: the single-trip targets
_COMMAND_MODULES += ("bench_validator",)  # csr bench-validator: the validator target
_COMMAND_MODULES += ("bench_variants",)  # csr bench-variants: foreign fleets through csr reconstruct
_COMMAND_MODULES += ("bench_budget",)  # csr bench-budget: where the mCD comes from
_COMMAND_MODULES += ("bench_http",)  # csr bench-http: response compression per coding
_COMMAND_MODULES += ("encode_trip",)  # csr encode-trip / decode-trip: the compact binary upload
_COMMAND_MODULES += ("bench_upload_size",)  # csr bench-upload-size: JSON vs binary bytes per km
_COMMAND_MODULES += ("bench_upload_memory",)  # csr bench-upload-memory: peak memory per upload
_COMMAND_MODULES += ("bench_lanelet2",)  # csr bench-lanelet2: the Lanelet2 export checked and routed
_COMMAND_MODULES += ("bench_storage",)  # csr bench-storage: stored bytes per km as passes accumulate
_COMMAND_MODULES += ("purge",)  # csr purge: erase a vehicle's data (services/cli/purge.py)
_COMMAND_MODULES += ("bench_uncertainty",)  # csr bench-uncertainty: sigma_abs_m calibration


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="csr", description="CSR crowdsourced road structure reconstruction")
    parser.add_argument("-v", "--verbose", action="store_true", help="debug logging")
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")
    for name in _COMMAND_MODULES:
        module = importlib.import_module(f"services.cli.{name}")
        module.register(sub)
    return parser


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    logging.basicConfig(
        level=logging.DEBUG if args.verbose else logging.INFO,
        format="%(asctime)s %(levelname)s %(name)s: %(message)s",
    )
    result = args.func(args)
    return int(result or 0)


if __name__ == "__main__":
    sys.exit(main())
