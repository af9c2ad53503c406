"""What registration errors cost the alignment: the same alignment with every accepted sub-map
registration replaced by the truth.

    python -m csr_core.alignment.evaluate_floor SCENARIO [--cache DIR] [--figure PNG] [--param NAME=VALUE ...]

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
RMS error and share of the squared error. Frames in the last three are held by their trips' own
GNSS (and the bias the graph learnt for each trip elsewhere).

``--figure PNG`` draws it: every frame on its true path, coloured by its stage and by its
aligned error. ``--param NAME=VALUE`` (repeatable) runs both alignments with that ``AlignmentParams`` field
changed, to compare a setting on the same single-trip results.

ATE as contract section 6: one rigid SE(2) over all frames of all aligned trips, then RMSE.
"""

from __future__ import annotations

import argparse
import json
import sys
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np

import csr_core.alignment as alignment
from csr_core import se2
from csr_core.alignment.evaluate_failures import single_trip_results
from csr_core.alignment.params import DEFAULT, AlignmentParams
from csr_core.metrics import apply_se2, umeyama_se2
from csr_core.param_overrides import replace_fields
from csr_core.scenario import read_poses_dir

OFF_M = 0.5  # a registration further than this from the truth counts as off


def true_poses(scenario: Path, frame, keys: Sequence[str]) -> dict[str, np.ndarray]:
    """Trip key -> true world_T_vehicle ``(N, 3)`` in ``frame`` (the pipeline's world frame)."""
    truth = read_poses_dir(scenario / "truth" / "poses")
    return {
        k: np.column_stack(
            [frame.to_local(truth[k].lonlat_deg), frame.yaw_rad(truth[k].heading_deg, truth[k].lonlat_deg)]
        )
        for k in keys
    }


def _true_relative(m, submaps, truth: Mapping[str, np.ndarray]) -> np.ndarray:
    si, sj = submaps[m.i], submaps[m.j]
    return se2.between(truth[si.trip_key][si.anchor_frame], truth[sj.trip_key][sj.anchor_frame])


def with_true_registration(m, submaps, truth: Mapping[str, np.ndarray]):
    """``m`` with ``delta_local_xyyaw`` such that ``m.relative_pose`` gives the truth."""
    si, sj = submaps[m.i], submaps[m.j]
    c = np.array([m.centre_xy_world[0], m.centre_xy_world[1], 0.0])
    gi, gj = si.world_T_submap - c, sj.world_T_submap - c
    delta = se2.compose(se2.compose(gi, _true_relative(m, submaps, truth)), se2.inverse(gj))
    return replace(m, delta_local_xyyaw=delta)


def align_with_matches(
    recons, change: Callable | None, seen: dict, params: AlignmentParams = DEFAULT
) -> alignment.AlignmentResult:
    """``align_trips`` with the matches handed to the pose graph passed through ``change``
    (and recorded in ``seen``)."""

    def inspect(matches, submaps):
        matches = [change(m, submaps) for m in matches] if change else list(matches)
        seen["submaps"], seen["matches"] = submaps, matches
        return matches

    return alignment.align_trips(recons, params=params, inspect_matches=inspect)


STAGES = ("registered", "not_registered", "failed_eq3", "no_candidate_pair")  # furthest first


def submap_stages(submaps, matches, diagnostics: Mapping) -> dict[int, str]:
    """Sub-map id -> the furthest step of Algorithm 1 one of its candidate pairs reached, from
    what ``align_trips`` reports (``candidate_pairs``, ``eq3_passed``) and the accepted ``matches``."""
    stage = {s.submap_id: "no_candidate_pair" for s in submaps}
    for (i, j), ok in zip(diagnostics["candidate_pairs"], diagnostics["eq3_passed"], strict=True):
        for s in (i, j):
            if ok or stage[s] == "no_candidate_pair":
                stage[s] = "not_registered" if ok else "failed_eq3"
    for m in matches:
        stage[m.i] = stage[m.j] = "registered"
    return stage


@dataclass(frozen=True, slots=True)
class FrameStages:
    """Every aligned frame: its true position, the index in ``STAGES`` of the furthest step a
    sub-map holding it reached, and its aligned error after the global SE(2) [m]."""

    true_xy_world: np.ndarray  # (N, 2)
    stage_index: np.ndarray  # (N,) int
    error_m: np.ndarray  # (N,)


def frame_stages(
    recons, seen: Mapping, result: alignment.AlignmentResult, truth: Mapping[str, np.ndarray]
) -> FrameStages:
    """``FrameStages`` of ``result``'s poses (``seen``: the sub-maps and matches ``_aligned`` recorded)."""
    poses = result.poses_xyyaw_world
    keys = sorted(poses)
    est = np.concatenate([poses[k][:, :2] for k in keys])
    g = umeyama_se2(est, np.concatenate([truth[k][:, :2] for k in keys]))
    stage = submap_stages(seen["submaps"], seen["matches"], result.diagnostics)
    rank = {name: n for n, name in enumerate(STAGES)}
    xy, idx, err = [], [], []
    for k, t in enumerate(recons):
        key = t.trip.key
        if key not in poses:
            continue
        best = np.full(len(poses[key]), len(STAGES) - 1)
        for s in seen["submaps"]:
            if s.trip_index == k:
                span = slice(s.first_frame, s.last_frame + 1)
                best[span] = np.minimum(best[span], rank[stage[s.submap_id]])
        xy.append(truth[key][:, :2])
        idx.append(best)
        err.append(np.linalg.norm(apply_se2(g, poses[key][:, :2]) - truth[key][:, :2], axis=1))
    return FrameStages(np.concatenate(xy), np.concatenate(idx), np.concatenate(err))


def error_by_stage(frames: FrameStages) -> dict[str, dict]:
    """Per stage: share of the frames, their RMS error, share of the squared error."""
    e2 = frames.error_m**2
    total = float(np.sum(e2))
    out = {}
    for n, name in enumerate(STAGES):
        mine = e2[frames.stage_index == n]
        out[name] = {
            "frames_share": len(mine) / len(e2),
            "rms_m": float(np.sqrt(np.mean(mine))) if len(mine) else float("nan"),
            "squared_error_share": float(np.sum(mine)) / total if total > 0 else 0.0,
        }
    return out


STAGE_COLOURS = {
    "registered": "tab:green",
    "not_registered": "tab:orange",
    "failed_eq3": "tab:red",
    "no_candidate_pair": "tab:purple",
}


def plot_frame_stages(frames: FrameStages, path: str | Path, title: str = "") -> Path:
    """Two panels over the true paths: each frame coloured by its stage (left; legend with the
    frames' share and RMS) and by its aligned error (right)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    summary = error_by_stage(frames)
    fig, (left, right) = plt.subplots(1, 2, figsize=(16, 8), sharex=True, sharey=True, layout="constrained")
    for n, name in enumerate(STAGES):
        m = frames.stage_index == n
        s = summary[name]
        label = f"{name}: {100 * s['frames_share']:.0f} % of frames" + (
            f", RMS {s['rms_m']:.2f} m" if m.any() else ""
        )
        left.scatter(*frames.true_xy_world[m].T, s=2, color=STAGE_COLOURS[name], label=label, rasterized=True)
    left.legend(loc="best", markerscale=6, fontsize=9)
    left.set_title("furthest step of Algorithm 1 a frame's sub-maps reached")
    order = np.argsort(frames.error_m)  # the largest errors drawn last, on top
    sc = right.scatter(
        *frames.true_xy_world[order].T,
        s=2,
        c=frames.error_m[order],
        cmap="viridis",
        vmin=0.0,
        vmax=max(0.5, float(np.percentile(frames.error_m, 99))),
        rasterized=True,
    )
    fig.colorbar(sc, ax=[left, right], label="aligned error after the global SE(2) [m]", shrink=0.8)
    right.set_title("aligned error")
    for ax in (left, right):
        ax.set_aspect("equal")
        ax.set_xlabel("x [m]")
    left.set_ylabel("y [m]")
    if title:
        fig.suptitle(title)
    path = Path(path)
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def ate_rmse_m(poses: Mapping[str, np.ndarray], truth: Mapping[str, np.ndarray]) -> float:
    keys = sorted(poses)
    est = np.concatenate([poses[k][:, :2] for k in keys])
    tru = np.concatenate([truth[k][:, :2] for k in keys])
    err = apply_se2(umeyama_se2(est, tru), est) - tru
    return float(np.sqrt(np.mean(np.sum(err**2, axis=1))))


def evaluate(
    scenario: Path, cache: Path | None = None, params: AlignmentParams = DEFAULT, figure: Path | None = None
) -> dict:
    """The module docstring's figures as a dict; ``figure``: also draw ``plot_frame_stages`` there."""
    frame, recons = single_trip_results(scenario, cache)
    truth = true_poses(scenario, frame, [r.trip.key for r in recons])
    as_is: dict = {}
    real = align_with_matches(recons, None, as_is, params)
    floor = align_with_matches(
        recons, lambda m, submaps: with_true_registration(m, submaps, truth), {}, params
    )
    off, along = 0, 0
    for m in as_is["matches"]:
        si, sj = as_is["submaps"][m.i], as_is["submaps"][m.j]
        err = se2.between(
            m.relative_pose(si.world_T_submap, sj.world_T_submap), _true_relative(m, as_is["submaps"], truth)
        )
        if np.hypot(err[0], err[1]) > OFF_M:  # in sub-map j's anchor frame: x along its heading
            off += 1
            along += int(abs(err[0]) > abs(err[1]))
    smoothed = {r.trip.key: r.poses_xyyaw_world for r in recons}
    stages = frame_stages(recons, as_is, real, truth)
    aligned_ate = ate_rmse_m(
        real.poses_xyyaw_world, truth
    )  # the contract's metric; the stages must add up to it
    if figure is not None:
        plot_frame_stages(stages, figure, f"{scenario.name}: aligned ATE {aligned_ate:.3f} m")
    return {
        "scenario": scenario.name,
        "trips": len(recons),
        "accepted_pairs": len(as_is["matches"]),
        "pairs_off_m": {"bound_m": OFF_M, "off": off, "mostly_along": along},
        "ate_rmse_m": {
            "smoothed": ate_rmse_m(smoothed, truth),
            "aligned": aligned_ate,
            "true_registrations": ate_rmse_m(floor.poses_xyyaw_world, truth),
        },
        "error_by_stage": error_by_stage(stages),
    }


def parse_params(assignments: Sequence[str]) -> AlignmentParams:
    """``--param`` assignments -> ``AlignmentParams`` (:func:`replace_fields` of ``DEFAULT``)."""
    return replace_fields(DEFAULT, assignments)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(
        prog="python -m csr_core.alignment.evaluate_floor",
        description=__doc__,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    ap.add_argument("scenario", type=Path, help="scenario folder (trips/, truth/)")
    ap.add_argument("--cache", type=Path, help="folder for cached single-trip results")
    ap.add_argument(
        "--param",
        action="append",
        default=[],
        metavar="NAME=VALUE",
        help="an AlignmentParams field to change for both alignments (repeatable)",
    )
    ap.add_argument(
        "--figure",
        type=Path,
        metavar="PNG",
        help="draw each frame by its stage and by its aligned error (plot_frame_stages)",
    )
    args = ap.parse_args(argv)
    try:
        params = parse_params(args.param)
    except ValueError as e:
        ap.error(str(e))
    sys.stdout.write(json.dumps(evaluate(args.scenario, args.cache, params, args.figure), indent=1) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
