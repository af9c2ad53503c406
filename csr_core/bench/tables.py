"""Markdown tables of the benchmark (paper Tables I-IV) and the BENCHMARKS.md section writer.

Summary rows average the per-scenario figures over the scenarios of the set (each scenario
weighs the same; NaN, i.e. "not scored", is skipped). Per-world rows follow.
"""

from __future__ import annotations

import math
import re
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from csr_core.bench.evaluate import EvaluatedOutput
from csr_core.bench.runner import Record
from csr_core.metrics import MCD_TYPES, TABLE_TYPES, MapScores, TrajectoryScores


def section_markers(set_name: str) -> tuple[str, str]:
    """The markers of one set's section of BENCHMARKS.md: each set has its own, so that
    ``csr bench --set dense --write`` leaves the ``standard-seeds`` tables alone."""
    return f"<!-- bench:{set_name}:begin -->", f"<!-- bench:{set_name}:end -->"


METHOD_NAMES = {
    "pipeline": "CSR pipeline",
    "gnss_only": "GNSS-only",
    "roadmap_icp": "RoadMap-style (ICP)",
}
SHORT = {
    "lane_divider": "ld",
    "centerline": "cl",
    "road_boundary": "bdr",
    "stop_line": "stop",
    "crosswalk": "cw",
}

# Paper figures (Tables I-IV), for side-by-side reading only: real data, different noise.
PAPER_MAP = {
    "RoadMap++ [paper]": (0.0636, 0.0611, 0.0824, 0.0690),
    "CSR [paper]": (0.0521, 0.0537, 0.0681, 0.0580),
}
PAPER_POSE = {"RoadMap++ [paper]": (0.194, 0.177, 0.107, 0.076), "CSR [paper]": (0.155, 0.135, 0.087, 0.056)}
PAPER_ABLATION = {"coarse only": (0.096, 0.064), "fine only": (0.111, 0.078), "coarse + fine": (0.087, 0.056)}


def fmt(value: float, digits: int = 3) -> str:
    if value is None or (isinstance(value, float) and math.isnan(value)):
        return "-"
    return f"{value:.{digits}f}"


def _mean(values: Sequence[float]) -> float:
    v = np.asarray([x for x in values if x is not None and not math.isnan(x)], float)
    return float(v.mean()) if v.size else float("nan")


def duration_text(seconds: float) -> str:
    """A run time as a reader wants it: seconds under two minutes, else whole minutes."""
    return f"{seconds:.0f} s" if seconds < 120 else f"{seconds / 60:.0f} min"


def markdown_table(header: Sequence[str], rows: Sequence[Sequence[str]]) -> str:
    lines = ["| " + " | ".join(header) + " |", "|" + "|".join(" --- " for _ in header) + "|"]
    lines += ["| " + " | ".join(r) + " |" for r in rows]
    return "\n".join(lines)


def _main_records(records: Sequence[Record]) -> list[Record]:
    return [r for r in records if not r.variant]


def _methods(records: Sequence[Record]) -> list[str]:
    seen: list[str] = []
    for r in records:
        if r.method not in seen:
            seen.append(r.method)
    return seen


def _map(r: Record, aligned: bool = True) -> MapScores | None:
    if not r.ok:
        return None
    return r.ev.evaluation.map_aligned if aligned else r.ev.evaluation.map_raw


def _traj(r: Record, aligned: bool) -> TrajectoryScores | None:
    if not r.ok:
        return None
    return r.ev.evaluation.aligned if aligned else r.ev.evaluation.raw


def _map_row(rs: Sequence[Record], aligned: bool = True) -> list[str]:
    maps = [m for m in (_map(r, aligned) for r in rs) if m is not None]
    cds = [fmt(_mean([m.per_type[t].cd for m in maps])) for t in TABLE_TYPES]
    compl = _mean([_mean([m.per_type[t].completeness for t in MCD_TYPES]) for m in maps])
    corr = _mean([_mean([m.per_type[t].correctness for t in MCD_TYPES]) for m in maps])
    return [*cds, fmt(_mean([m.mcd for m in maps])), fmt(compl, 2), fmt(corr, 2)]


def _pose_row(rs: Sequence[Record], aligned: bool) -> list[str]:
    ts = [t for t in (_traj(r, aligned) for r in rs) if t is not None]
    cov = _mean([r.ev.evaluation.coverage for r in rs if r.ok])
    return [
        fmt(_mean([t.ate.rmse for t in ts])),
        fmt(_mean([t.ate.mean for t in ts])),
        fmt(_mean([t.rpe.rmse for t in ts])),
        fmt(_mean([t.rpe.mean for t in ts])),
        fmt(cov, 2),
    ]


def _cost_row(rs: Sequence[Record]) -> list[str]:
    ok = [r for r in rs if r.ok]
    km = sum(r.km for r in ok)
    if not ok or km <= 0:
        return ["-"] * 6
    wall = sum(r.run.wall_s for r in ok)
    proc = sum(r.report.get("timings_s", {}).get("reconstruct", float("nan")) for r in ok)
    up = sum(r.uploaded_bytes for r in ok)
    out = sum(r.output_bytes for r in ok)
    return [
        fmt(wall / km, 2),
        fmt(proc / km, 2),
        fmt(up / km / 1e6, 2),
        fmt(out / km / 1e6, 3),
        fmt((up + out) / km / 1e6, 2),
        fmt(max(r.run.peak_rss_mb for r in ok), 0),
    ]


def table_map(records: Sequence[Record], aligned: bool = True) -> str:
    main = _main_records(records)
    header = ["method", *[f"CD_{SHORT[t.value]}" for t in TABLE_TYPES], "mCD", "completeness", "correctness"]
    rows = [
        [METHOD_NAMES.get(m, m), *_map_row([r for r in main if r.method == m], aligned)]
        for m in _methods(main)
    ]
    if aligned:
        rows += [
            [name, fmt(v[0], 4), fmt(v[1], 4), fmt(v[2], 4), "", "", fmt(v[3], 4), "", ""]
            for name, v in PAPER_MAP.items()
        ]
    return markdown_table(header, rows)


def table_pose(records: Sequence[Record]) -> str:
    main = _main_records(records)
    header = ["method", "frames", "ATE RMSE", "ATE ME", "RPE RMSE", "RPE ME", "coverage"]
    rows = []
    for m in _methods(main):
        rs = [r for r in main if r.method == m]
        for aligned in (False, True):
            rows.append([METHOD_NAMES.get(m, m), "aligned" if aligned else "raw", *_pose_row(rs, aligned)])
    rows += [[name, "(paper)", *[fmt(x) for x in v], ""] for name, v in PAPER_POSE.items()]
    return markdown_table(header, rows)


def table_cost(records: Sequence[Record]) -> str:
    main = _main_records(records)
    header = [
        "method",
        "wall s/km",
        "processing s/km",
        "uploaded MB/km",
        "output MB/km",
        "stored MB/km",
        "peak memory MB",
    ]
    rows = [[METHOD_NAMES.get(m, m), *_cost_row([r for r in main if r.method == m])] for m in _methods(main)]
    rows.append(["CSR [paper]", "17.1 (0.285 min/km)", "", "", "", "27 (0.027 Gb/km, read as GB)", ""])
    rows.append(["traditional LiDAR [paper]", "352.9 (5.881 min/km)", "", "", "", "2400 (2.4 Gb/km)", ""])
    return markdown_table(header, rows)


def table_ablation(records: Sequence[Record]) -> str | None:
    variants = [r for r in records if r.method == "pipeline" and r.variant]
    if not variants:
        return None
    full = [r for r in records if r.method == "pipeline" and not r.variant]
    rows = []
    for name, paper in PAPER_ABLATION.items():
        rs = full if name == "coarse + fine" else [r for r in variants if r.variant == name]
        ts = [t for t in (_traj(r, True) for r in rs) if t is not None]
        rows.append(
            [
                name,
                fmt(_mean([t.rpe.rmse for t in ts])),
                fmt(_mean([t.rpe.mean for t in ts])),
                fmt(paper[0]),
                fmt(paper[1]),
            ]
        )
    return markdown_table(["alignment", "RPE RMSE", "RPE ME", "paper RPE RMSE", "paper RPE ME"], rows)


def worst_trip_rmse_m(ev: EvaluatedOutput) -> float:
    """The largest per-trip position RMSE (metres, raw: no alignment to the truth) of a run."""
    errors = [
        float(np.sqrt(np.mean(np.sum((est - ev.true_xy_by_key[k]) ** 2, axis=1))))
        for k, est in ev.est_xy_by_key.items()
        if len(est)
    ]
    return max(errors) if errors else float("nan")


def table_per_world(records: Sequence[Record]) -> str:
    """One row per scenario and method; "worst trip" is the largest raw per-trip position RMSE
    and "marked" the trips the run reported failed or degraded."""
    main = _main_records(records)
    header = [
        "scenario",
        "method",
        "km",
        "trips/place",
        "mCD",
        "compl.",
        "corr.",
        "ATE RMSE",
        "RPE RMSE",
        "worst trip",
        "marked",
        "coverage",
        "wall s",
    ]
    rows = []
    for r in main:
        if not r.ok:
            rows.append(
                [
                    r.scenario,
                    METHOD_NAMES.get(r.method, r.method),
                    "-",
                    "",
                    "failed",
                    "",
                    "",
                    "",
                    "",
                    "",
                    "",
                    "",
                    fmt(r.run.wall_s, 1),
                ]
            )
            continue
        ev = r.ev.evaluation
        m = ev.map_aligned
        rows.append(
            [
                r.scenario,
                METHOD_NAMES.get(r.method, r.method),
                fmt(r.km, 1),
                fmt(r.ev.trips_per_place, 0),
                fmt(m.mcd),
                fmt(_mean([m.per_type[t].completeness for t in MCD_TYPES]), 2),
                fmt(_mean([m.per_type[t].correctness for t in MCD_TYPES]), 2),
                fmt(ev.aligned.ate.rmse),
                fmt(ev.aligned.rpe.rmse),
                fmt(worst_trip_rmse_m(r.ev), 2),
                str(len(r.report.get("failed", {})) + len(r.report.get("degraded", {}))),
                fmt(ev.coverage, 2),
                fmt(r.run.wall_s, 1),
            ]
        )
    return markdown_table(header, rows)


def replace_section(document: str, section: str, begin: str, end: str) -> str:
    """Replace the text between ``begin`` and ``end`` (markers kept); append if absent. Everything
    outside the markers is preserved byte for byte."""
    block = f"{begin}\n{section.strip()}\n{end}"
    pattern = re.compile(re.escape(begin) + r".*?" + re.escape(end), re.DOTALL)
    if pattern.search(document):
        return pattern.sub(lambda _: block, document, count=1)
    sep = "" if not document or document.endswith("\n\n") else ("\n" if document.endswith("\n") else "\n\n")
    return f"{document}{sep}{block}\n"


def write_section(path: Path, section: str, set_name: str) -> None:
    text = path.read_text() if path.exists() else "# Benchmarks\n\n"
    path.write_text(replace_section(text, section, *section_markers(set_name)))
