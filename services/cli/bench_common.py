"""What the ``csr bench-*`` commands that write one BENCHMARKS.md section share: the work-folder,
parallelism, markdown and figure arguments, a progress printer, and printing and writing the
section. Not a command itself (``_COMMAND_MODULES`` does not list it)."""

from __future__ import annotations

import argparse
import logging
import sys
import time
from collections.abc import Callable
from pathlib import Path

#: the stages that log a line per trip or per stage; a bench quiets them
STAGE_LOGGERS = ("csr_core.single_trip", "csr_core.alignment", "csr_core.topology")


def add_output_arguments(
    p: argparse.ArgumentParser,
    out_help: str,
    write_help: str,
    jobs_help: str = "scenarios evaluated in parallel (processes; default 2)",
) -> None:
    """``--out``, ``--jobs``, ``--write MARKDOWN`` and ``--figures``."""
    p.add_argument("--out", default="bench-out", help=out_help)
    p.add_argument("--jobs", type=int, default=2, help=jobs_help)
    p.add_argument("--write", metavar="MARKDOWN", help=write_help)
    p.add_argument("--figures", default="docs/figures", help="where the PNG figure goes")


def quiet_stage_logs(names: tuple[str, ...] = STAGE_LOGGERS) -> None:
    for name in names:
        logging.getLogger(name).setLevel(logging.WARNING)


def progress_printer(t0: float) -> Callable[[str], None]:
    """Prints ``[seconds since t0] message`` to stderr."""
    return lambda msg: print(f"[{time.perf_counter() - t0:6.0f} s] {msg}", file=sys.stderr)


def doc_dir(write: str | None) -> Path:
    """The folder the section's figure links are relative to: the markdown's, or the current one."""
    return Path(write).parent if write else Path(".")


def publish(section: str, write: str | None, section_name: str, command: str) -> None:
    """Print the section and, with ``--write``, put it in place of its markers in that file."""
    from csr_core.bench.tables import write_section

    print(section)
    if write:
        write_section(Path(write), section, section_name)
        print(f"csr {command}: wrote the {section_name} section of {write}", file=sys.stderr)
