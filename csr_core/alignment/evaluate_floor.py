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

Also printed, ``error_by_stage``: where the aligned error sits. Each frame goes with the furthest
step of Algorithm 1 that a sub-map holding it reached (``registered`` in an accepted pair,
``not_registered``: a candidate pair passed Eq. 3 but none was accepted, ``failed_eq3``: its
candidate pairs all failed Eq. 3 or the vote, ``no_candidate_pair``), with the frames' share,
RMS error and share of the squared error. A region whose error is in the first three is held by
its trips' own GNSS.

``--param NAME=VALUE`` (repeatable) runs both alignments with that ``AlignmentParams`` field
changed, to compare a setting on the same single-trip results.

ATE as contract section 6: one rigid SE(2) over all frames of all aligned trips, then RMSE.
"""

from __future__ import annotations

import argparse
import json
import sys
from collections.abc import Callable, Mapping, Sequence
from dataclasses import fields, replace
from pathlib import Path

import numpy as np

import csr_core.alignment as alignment
from csr_core import se2
from csr_core.alignment.evaluate_failures import single_trip_results
from csr_core.alignment.fine import dash_ends, detections
from csr_core.alignment.params import DEFAULT, AlignmentParams, noise_scales
from csr_core.alignment.submaps import split_submaps, submap_pairs
from csr_core.alignment.topology import topology_filter
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


def _aligned(recons, change: Callable | None, seen: dict,
             params: AlignmentParams = DEFAULT) -> alignment.AlignmentResult:
    """``align_trips`` with the matches handed to the pose graph passed through ``change``
    (and recorded in ``seen``)."""

    def inspect(matches, submaps):
        matches = [change(m, submaps) for m in matches] if change else list(matches)
        seen["submaps"], seen["matches"] = submaps, matches
        return matches

    return alignment.align_trips(recons, params=params, inspect_matches=inspect)


STAGES = ("registered", "not_registered", "failed_eq3", "no_candidate_pair")  # furthest first


def submap_stages(recons, matches, params: AlignmentParams) -> dict[int, str]:
    """Sub-map id -> the furthest step of Algorithm 1 one of its candidate pairs reached
    (sub-maps, pairs and Eq. 3 computed again as ``align_trips`` does; they are deterministic)."""
    dashes = ([dash_ends(t, dets=detections(t)) for t in recons]
              if (params.landmarks and params.coarse) or params.fine_dashes else None)
    circles, submaps = split_submaps(recons, params, dashes)
    pairs = submap_pairs(submaps, params)
    passed = topology_filter(pairs, submaps, circles, recons, noise_scales(recons, params), params)
    stage = {s.submap_id: "no_candidate_pair" for s in submaps}
    for (i, j), ok in zip(pairs, passed, strict=True):
        for s in (i, j):
            if ok or stage[s] == "no_candidate_pair":
                stage[s] = "not_registered" if ok else "failed_eq3"
    for m in matches:
        stage[m.i] = stage[m.j] = "registered"
    return stage


def error_by_stage(recons, seen: Mapping, poses: Mapping[str, np.ndarray], truth: Mapping[str, np.ndarray],
                   params: AlignmentParams) -> dict[str, dict]:
    """Frames grouped by the furthest stage a sub-map holding them reached (module docstring)."""
    keys = sorted(poses)
    est = np.concatenate([poses[k][:, :2] for k in keys])
    g = umeyama_se2(est, np.concatenate([truth[k][:, :2] for k in keys]))
    stage = submap_stages(recons, seen["matches"], params)
    rank = {name: n for n, name in enumerate(STAGES)}
    sq: dict[str, list[np.ndarray]] = {name: [] for name in STAGES}
    for k, t in enumerate(recons):
        key = t.trip.key
        if key not in poses:
            continue
        best = np.full(len(poses[key]), len(STAGES) - 1)
        for s in seen["submaps"]:
            if s.trip_index == k:
                span = slice(s.first_frame, s.last_frame + 1)
                best[span] = np.minimum(best[span], rank[stage[s.submap_id]])
        err2 = np.sum((apply_se2(g, poses[key][:, :2]) - truth[key][:, :2]) ** 2, axis=1)
        for n, name in enumerate(STAGES):
            sq[name].append(err2[best == n])
    total = sum(float(np.sum(np.concatenate(v))) for v in sq.values())
    n_frames = sum(len(np.concatenate(v)) for v in sq.values())
    out = {}
    for name, parts in sq.items():
        e2 = np.concatenate(parts)
        out[name] = {"frames_share": len(e2) / n_frames,
                     "rms_m": float(np.sqrt(np.mean(e2))) if len(e2) else float("nan"),
                     "squared_error_share": float(np.sum(e2)) / total if total > 0 else 0.0}
    return out


def ate_rmse_m(poses: Mapping[str, np.ndarray], truth: Mapping[str, np.ndarray]) -> float:
    keys = sorted(poses)
    est = np.concatenate([poses[k][:, :2] for k in keys])
    tru = np.concatenate([truth[k][:, :2] for k in keys])
    err = apply_se2(umeyama_se2(est, tru), est) - tru
    return float(np.sqrt(np.mean(np.sum(err**2, axis=1))))


def evaluate(scenario: Path, cache: Path | None = None, params: AlignmentParams = DEFAULT) -> dict:
    frame, recons = single_trip_results(scenario, cache)
    truth = true_poses(scenario, frame, [r.trip.key for r in recons])
    as_is: dict = {}
    real = _aligned(recons, None, as_is, params)
    floor = _aligned(recons, lambda m, submaps: _with_true_registration(m, submaps, truth), {}, params)
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
                           "true_registrations": ate_rmse_m(floor.poses_xyyaw_world, truth)},
            "error_by_stage": error_by_stage(recons, as_is, real.poses_xyyaw_world, truth, params)}


def parse_params(assignments: Sequence[str]) -> AlignmentParams:
    """``["name=value", ...]`` -> ``AlignmentParams`` with those fields changed (values read as
    the field's default's type)."""
    defaults = {f.name: getattr(DEFAULT, f.name) for f in fields(AlignmentParams)}
    changes: dict = {}
    for a in assignments:
        name, sep, value = a.partition("=")
        if not sep or name not in defaults:
            raise ValueError(f"--param {a!r}: expected NAME=VALUE with NAME a field of AlignmentParams")
        kind = type(defaults[name])
        changes[name] = value.lower() in ("1", "true", "yes") if kind is bool else kind(value)
    return replace(DEFAULT, **changes)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m csr_core.alignment.evaluate_floor", description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("scenario", type=Path, help="scenario folder (trips/, truth/)")
    ap.add_argument("--cache", type=Path, help="folder for cached single-trip results")
    ap.add_argument("--param", action="append", default=[], metavar="NAME=VALUE",
                    help="an AlignmentParams field to change for both alignments (repeatable)")
    args = ap.parse_args(argv)
    try:
        params = parse_params(args.param)
    except ValueError as e:
        ap.error(str(e))
    sys.stdout.write(json.dumps(evaluate(args.scenario, args.cache, params), indent=1) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
