"""What registration errors cost the alignment: the same alignment with every accepted sub-map
registration replaced by the truth.

    python -m csr_core.alignment.evaluate_floor SCENARIO [--cache DIR]

The single-trip stage and :func:`csr_core.alignment.align_trips` run as ``csr reconstruct``
does (``evaluate_failures.single_trip_results``), twice:

- **as is**;
- **true registrations**: each accepted pair's ``T_reg^{i,j}`` (Eq. 9's e^reg) is replaced by
  the true relative pose of the two sub-maps' anchor frames; the pairs, their information
  (Eq. 12), the GNSS priors (Eq. 10-11) and the fine stage are unchanged.

The second ATE is the best these pairs and the trips' GNSS allow: what is left once every
registration is exact is the error of the GNSS fixes that the pose graph averages. If the two
are close, better registration cannot help; more trips, or better GNSS, can. Also printed: how
many accepted registrations are more than 0.5 m off the truth, and how many of those are off
along the road mostly (a registration's weak direction, which its information down-weights).

ATE as contract section 6: one rigid SE(2) over all frames of all aligned trips, then RMSE.
"""

from __future__ import annotations

import argparse
import json
import sys
from collections.abc import Callable, Mapping, Sequence
from dataclasses import replace
from pathlib import Path

import numpy as np

import csr_core.alignment as alignment
from csr_core import se2
from csr_core.alignment.evaluate_failures import single_trip_results
from csr_core.metrics import apply_se2, umeyama_se2
from csr_core.scenario import read_poses_dir
from csr_core.se2 import heading_deg_to_yaw_rad

OFF_M = 0.5  # a registration further than this from the truth counts as off


def true_poses(scenario: Path, frame, keys: Sequence[str]) -> dict[str, np.ndarray]:
    """Trip key -> true world_T_vehicle ``(N, 3)`` in ``frame`` (the pipeline's world frame)."""
    truth = read_poses_dir(scenario / "truth" / "poses")
    return {k: np.column_stack([frame.to_local(truth[k].lonlat_deg), heading_deg_to_yaw_rad(truth[k].heading_deg)])
            for k in keys}


def _true_relative(m, submaps, truth: Mapping[str, np.ndarray]) -> np.ndarray:
    si, sj = submaps[m.i], submaps[m.j]
    return se2.between(truth[si.trip_key][si.anchor_frame], truth[sj.trip_key][sj.anchor_frame])


def _with_true_registration(m, submaps, truth: Mapping[str, np.ndarray]):
    """``m`` with ``delta_local_xyyaw`` such that ``m.relative_pose`` gives the truth."""
    si, sj = submaps[m.i], submaps[m.j]
    c = np.array([m.centre_xy_world[0], m.centre_xy_world[1], 0.0])
    gi, gj = si.world_T_submap - c, sj.world_T_submap - c
    delta = se2.compose(se2.compose(gi, _true_relative(m, submaps, truth)), se2.inverse(gj))
    return replace(m, delta_local_xyyaw=delta)


def _aligned(recons, change: Callable | None, seen: dict) -> alignment.AlignmentResult:
    """``align_trips`` with the matches handed to the pose graph passed through ``change``
    (and recorded in ``seen``)."""

    def inspect(matches, submaps):
        matches = [change(m, submaps) for m in matches] if change else list(matches)
        seen["submaps"], seen["matches"] = submaps, matches
        return matches

    return alignment.align_trips(recons, inspect_matches=inspect)


def ate_rmse_m(poses: Mapping[str, np.ndarray], truth: Mapping[str, np.ndarray]) -> float:
    keys = sorted(poses)
    est = np.concatenate([poses[k][:, :2] for k in keys])
    tru = np.concatenate([truth[k][:, :2] for k in keys])
    err = apply_se2(umeyama_se2(est, tru), est) - tru
    return float(np.sqrt(np.mean(np.sum(err**2, axis=1))))


def evaluate(scenario: Path, cache: Path | None = None) -> dict:
    frame, recons = single_trip_results(scenario, cache)
    truth = true_poses(scenario, frame, [r.trip.key for r in recons])
    as_is: dict = {}
    real = _aligned(recons, None, as_is)
    floor = _aligned(recons, lambda m, submaps: _with_true_registration(m, submaps, truth), {})
    off, along = 0, 0
    for m in as_is["matches"]:
        si, sj = as_is["submaps"][m.i], as_is["submaps"][m.j]
        err = se2.between(m.relative_pose(si.world_T_submap, sj.world_T_submap), _true_relative(m, as_is["submaps"], truth))
        if np.hypot(err[0], err[1]) > OFF_M:  # in sub-map j's anchor frame: x along its heading
            off += 1
            along += int(abs(err[0]) > abs(err[1]))
    smoothed = {r.trip.key: r.poses_xyyaw_world for r in recons}
    return {"scenario": scenario.name, "trips": len(recons), "accepted_pairs": len(as_is["matches"]),
            "pairs_off_m": {"bound_m": OFF_M, "off": off, "mostly_along": along},
            "ate_rmse_m": {"smoothed": ate_rmse_m(smoothed, truth), "aligned": ate_rmse_m(real.poses_xyyaw_world, truth),
                           "true_registrations": ate_rmse_m(floor.poses_xyyaw_world, truth)}}


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m csr_core.alignment.evaluate_floor", description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("scenario", type=Path, help="scenario folder (trips/, truth/)")
    ap.add_argument("--cache", type=Path, help="folder for cached single-trip results")
    args = ap.parse_args(argv)
    sys.stdout.write(json.dumps(evaluate(args.scenario, args.cache), indent=1) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
