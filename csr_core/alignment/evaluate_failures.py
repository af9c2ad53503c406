"""Per-trip accuracy of an alignment against a scenario's truth, and which trips were marked failed.

    python -m csr_core.alignment.evaluate_failures SCENARIO [--out OUT] [--cache DIR]

With ``--out`` (a ``csr reconstruct`` output folder) it reads the poses CSVs and
``report.json``'s ``failed``; a failed trip has no poses, so its ATE is not shown. Without it,
the single-trip stage and :func:`csr_core.alignment.align_trips` run in this process (as
``csr reconstruct`` does; ``--cache`` keeps the single-trip results between runs) and a failed
trip's ATE is read from its unaligned poses (``diagnostics["unaligned_poses"]``).

ATE as contract section 6: one rigid SE(2) fitted on every frame of every trip *with* poses
(failed trips left out), then per-trip RMSE. Also printed: the mean error along and across the
true heading (an along-track offset is what an unobservable trip shows).
"""

from __future__ import annotations

import argparse
import hashlib
import json
import pickle
import sys
from collections.abc import Mapping
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np

from csr_core.metrics import apply_se2, umeyama_se2
from csr_core.scenario import list_trip_files, load_trip, read_poses_dir, read_scenario_meta
from csr_core.single_trip.params import DEFAULT as SINGLE_TRIP_DEFAULT
from csr_core.single_trip.params import SingleTripParams

#: the hard-profile rule: a trip with poses must be under this ATE
ATE_BOUND_M = 0.5


@dataclass(frozen=True, slots=True)
class TripScore:
    key: str
    ate_rmse_m: float  # NaN when the trip has no poses to score
    along_mean_m: float
    across_mean_m: float
    failed_reason: str | None  # None: the trip has poses (aligned, or unaligned with no_overlap)
    unaligned_reason: str | None = (
        None  # no_overlap: it has poses, its own smoothed ones (nothing checked them)
    )


def score_trips(
    true_xy: Mapping[str, np.ndarray],
    true_yaw: Mapping[str, np.ndarray],
    est_xy: Mapping[str, np.ndarray],
    failed: Mapping[str, str],
    failed_xy: Mapping[str, np.ndarray] | None = None,
    unaligned: Mapping[str, str] | None = None,
) -> list[TripScore]:
    """Per-trip ATE after one SE(2) over the trips with poses (``est_xy``); ``failed_xy`` (the
    failed trips' unaligned poses, optional) are moved by the same transform and scored too;
    ``unaligned``: trips with poses that nothing aligned (``no_overlap``), with the reason."""
    unaligned = unaligned or {}
    keys = [k for k in true_xy if k in est_xy]
    truth_T_est = umeyama_se2(
        np.concatenate([est_xy[k] for k in keys]), np.concatenate([true_xy[k] for k in keys])
    )
    out = []
    for k in true_xy:
        xy = est_xy.get(k, (failed_xy or {}).get(k))
        if xy is None:
            out.append(
                TripScore(k, float("nan"), float("nan"), float("nan"), failed.get(k), unaligned.get(k))
            )
            continue
        err = apply_se2(truth_T_est, xy) - true_xy[k]
        c, s = np.cos(true_yaw[k]), np.sin(true_yaw[k])
        along, across = err[:, 0] * c + err[:, 1] * s, -err[:, 0] * s + err[:, 1] * c
        out.append(
            TripScore(
                k,
                float(np.sqrt(np.mean(np.sum(err**2, axis=1)))),
                float(along.mean()),
                float(across.mean()),
                failed.get(k),
                unaligned.get(k),
            )
        )
    return out


def _truth(scenario: Path):
    meta = read_scenario_meta(scenario)
    tracks = read_poses_dir(scenario / "truth" / "poses")
    xy = {k: meta.frame.to_local(t.lonlat_deg) for k, t in tracks.items()}
    # heading_deg is clockwise from true north -> yaw in the plane, counter-clockwise from grid east
    yaw = {k: meta.frame.yaw_rad(t.heading_deg, t.lonlat_deg) for k, t in tracks.items()}
    return meta, xy, yaw


def evaluate_output(scenario: Path, out: Path) -> list[TripScore]:
    """Scores of a ``csr reconstruct`` output folder (failed trips: no poses, no ATE)."""
    meta, true_xy, true_yaw = _truth(scenario)
    est = read_poses_dir(out / "poses")
    report = json.loads((out / "report.json").read_text())
    return score_trips(
        true_xy,
        true_yaw,
        {k: meta.frame.to_local(t.lonlat_deg) for k, t in est.items()},
        report.get("failed", {}),
        unaligned=report.get("diagnostics", {}).get("unaligned", {}),
    )


def single_trip_results(scenario: Path, cache: Path | None, params: SingleTripParams = SINGLE_TRIP_DEFAULT):
    """``(world frame, [TripReconstruction])`` as ``csr reconstruct`` computes them (with
    ``params``), cached: one file per scenario and, for other than the default params, per params."""
    from csr_core.pipeline import world_frame
    from csr_core.single_trip import reconstruct_trip

    name = scenario.resolve().name
    if params != SINGLE_TRIP_DEFAULT:  # the dataclass's repr names every field's value
        name += "-" + hashlib.sha1(repr(params).encode()).hexdigest()[:12]
    path = cache / (name + ".pkl") if cache else None
    if path is not None and path.exists():
        return pickle.loads(path.read_bytes())
    trips = [load_trip(f) for f in list_trip_files(scenario)]
    frame = world_frame(trips)
    result = (frame, [reconstruct_trip(t, frame, params) for t in trips])
    if path is not None:
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_bytes(pickle.dumps(result))
    return result


def evaluate_in_process(
    scenario: Path, cache: Path | None = None, mark_unobservable: bool = False
) -> tuple[list[TripScore], object]:
    """Single-trip + ``align_trips`` here; failed trips scored on their unaligned poses."""
    from csr_core.alignment import DEFAULT, align_trips
    from csr_core.pipeline import poses_after_alignment

    meta, true_xy, true_yaw = _truth(scenario)
    frame, recons = single_trip_results(scenario, cache)
    res = align_trips(recons, params=replace(DEFAULT, mark_unobservable=mark_unobservable))
    to_scenario = lambda p: meta.frame.to_local(frame.to_lonlat(p[:, :2]))  # noqa: E731
    poses, failed, no_overlap = poses_after_alignment(recons, res)  # as the pipeline keeps them
    est = {k: to_scenario(p) for k, p in poses.items()}
    unaligned = {k: to_scenario(p) for k, p in res.diagnostics["unaligned_poses"].items() if k in failed}
    return score_trips(true_xy, true_yaw, est, failed, unaligned, no_overlap), res


def format_scores(scores: list[TripScore]) -> str:
    lines = [f"{'trip':<24} {'ATE m':>7} {'along':>7} {'across':>7}  status"]
    for s in scores:
        status = (
            f"FAILED ({s.failed_reason})"
            if s.failed_reason
            else f"unaligned, own poses ({s.unaligned_reason.split(':')[0]})"
            if s.unaligned_reason
            else "ok"
        )
        flag = " <-- over bound" if not s.failed_reason and s.ate_rmse_m > ATE_BOUND_M else ""
        lines.append(
            f"{s.key:<24} {s.ate_rmse_m:7.3f} {s.along_mean_m:+7.3f} {s.across_mean_m:+7.3f}  {status}{flag}"
        )
    kept = [s.ate_rmse_m for s in scores if not s.failed_reason]
    marked = sum(1 for s in scores if s.failed_reason)
    lines.append(
        f"trips {len(scores)}, marked failed {marked} ({marked / len(scores):.0%}), "
        f"worst unmarked ATE {max(kept) if kept else float('nan'):.3f} m, "
        f"unmarked over {ATE_BOUND_M} m: {sum(1 for a in kept if a > ATE_BOUND_M)} "
        f"(of them unaligned with their own poses: "
        f"{sum(1 for s in scores if not s.failed_reason and s.unaligned_reason and s.ate_rmse_m > ATE_BOUND_M)})"
    )
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(
        prog="python -m csr_core.alignment.evaluate_failures",
        description=__doc__,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    ap.add_argument("scenario", type=Path, help="scenario folder (trips/, truth/)")
    ap.add_argument("--out", type=Path, help="a csr reconstruct output folder (else: align in this process)")
    ap.add_argument("--cache", type=Path, help="folder for cached single-trip results (in-process mode)")
    ap.add_argument(
        "--mark-unobservable", action="store_true", help="mark trips held only by their own GNSS failed"
    )
    args = ap.parse_args(argv)
    if args.out is not None:
        scores = evaluate_output(args.scenario, args.out)
    else:
        scores, _ = evaluate_in_process(args.scenario, args.cache, args.mark_unobservable)
    sys.stdout.write(format_scores(scores) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
