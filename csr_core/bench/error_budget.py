"""Where the map's error comes from: the map's mCD split into what the poses and what the
element stages leave (``csr bench-budget``).

Each scenario's trips are fused three times, as ``csr reconstruct`` fuses them
(``pipeline.fuse_trips``), on three sets of poses:

- **pipeline**: the single-trip stage, then ``align_trips`` (coarse and fine) as it runs;
- **exact registrations**: the same, with every accepted sub-map registration (Eq. 9's
  ``T_reg``) replaced by the true relative pose (``alignment.evaluate_floor``): the pairs, their
  information and the GNSS priors unchanged. What is left is the error of the trips' GNSS that
  the pose graph averages: the floor of any registration;
- **true poses**: the smoothing replaced by the true poses (``SmoothedPoses.given``), the
  element stages (tracking, splicing, fusion) as they are: what perception noise and the
  element stages alone leave. Also scored: the same trips' instances overlaid, not fused.

Every map is scored as contract section 6 scores ``csr reconstruct``'s (one rigid SE(2) of all
poses onto the truth, applied to the map; ``metrics.map_scores``), with the ATE of the poses.
The gap between *pipeline* and *exact registrations* is what better matching could still gain;
the gap between *exact registrations* and *true poses* is the trips' GNSS, which more trips
(not better code) would lower.
"""

from __future__ import annotations

import os
import pickle
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from csr_core.bench.runner import (
    ensure_scenario,
    map_in_processes,
    simulator_fingerprint,
    sources_fingerprint,
)
from csr_core.bench.sets import ScenarioSpec, scenario_set
from csr_core.bench.tables import duration_text, markdown_table

SECTION = "error-budget"  # the standard-seeds section; other sets get their own (section_name)
MCD_TARGET_M = 0.045  # the target: mCD <= 0.045 m on the standard profile
#: what the cached single-trip results depend on (both the smoothed and the true-pose ones)
CACHE_SOURCES = ("single_trip", "types.py", "se2.py", "geo.py", "upload.py", "scenario.py", "pipeline.py")
#: the three poses the trips are fused on, in the table's order
POSES = ("pipeline", "exact_registrations", "true_poses")


def section_name(set_name: str) -> str:
    """The BENCHMARKS.md section of ``set_name``'s budget (each set has its own)."""
    return SECTION if set_name == "standard-seeds" else f"{SECTION}-{set_name}"


def figure_name(set_name: str) -> str:
    return "bench_error_budget.png" if set_name == "standard-seeds" else f"bench_error_budget_{set_name}.png"


@dataclass(frozen=True, slots=True)
class Job:
    spec: ScenarioSpec
    scenario_dir: Path
    cache_dir: Path


def _true_pose_cache(cache_dir: Path | None, scenario_dir: Path) -> Path | None:
    """Where a scenario's single-trip results on the true poses are cached (none without a folder)."""
    return cache_dir / f"{scenario_dir.resolve().name}-true-poses.pkl" if cache_dir is not None else None


def _true_pose_recons(recons: Sequence, frame, truth: dict[str, np.ndarray], path: Path | None) -> list:
    """The single-trip stage of every trip with its smoothing replaced by the true poses (cached)."""
    from csr_core.single_trip import reconstruct_trip
    from csr_core.single_trip.pose_graph import SmoothedPoses

    if path is not None and path.exists():
        return pickle.loads(path.read_bytes())
    out = [reconstruct_trip(r.trip, frame, smoothed=SmoothedPoses.given(truth[r.trip.key])) for r in recons]
    if path is not None:
        path.write_bytes(pickle.dumps(out))
    return out


def scenario_budget(scenario_dir: Path, cache_dir: Path | None = None) -> dict:
    """The module docstring's maps of one scenario: ``{"trips", "mcd": {pose set: m},
    "mcd_true_poses_overlaid", "ate_rmse_m": {"pipeline", "exact_registrations"}}``; the
    single-trip results cached in ``cache_dir`` when given."""
    from csr_core import metrics
    from csr_core.alignment.evaluate_failures import single_trip_results
    from csr_core.alignment.evaluate_floor import (
        align_with_matches,
        ate_rmse_m,
        true_poses,
        with_true_registration,
    )
    from csr_core.bench.evaluate import trips_per_place
    from csr_core.pipeline import fuse_trips, poses_after_alignment
    from csr_core.scenario import geo_features_to_local, read_map_geojson
    from csr_core.types import MapFeature

    if cache_dir is not None:
        cache_dir.mkdir(parents=True, exist_ok=True)
    frame, recons = single_trip_results(scenario_dir, cache_dir)
    truth = true_poses(scenario_dir, frame, [r.trip.key for r in recons])
    truth_map = geo_features_to_local(read_map_geojson(scenario_dir / "truth" / "map.geojson"), frame)
    true_xy = np.concatenate([truth[k][:, :2] for k in sorted(truth)])

    def mcd(features, poses_by_key: dict[str, np.ndarray]) -> float:
        keys = sorted(poses_by_key)
        truth_T_est = metrics.umeyama_se2(
            np.concatenate([poses_by_key[k][:, :2] for k in keys]),
            np.concatenate([truth[k][:, :2] for k in keys]),
        )
        return metrics.map_scores(metrics.transform_features(truth_T_est, features), truth_map, true_xy).mcd

    out: dict = {
        "trips": len(recons),
        "trips_per_place": trips_per_place({k: v[:, :2] for k, v in truth.items()}),
        "mcd": {},
        "ate_rmse_m": {},
    }
    for name, change in (
        ("pipeline", None),
        ("exact_registrations", lambda m, submaps: with_true_registration(m, submaps, truth)),
    ):
        aligned = align_with_matches(recons, change, {})
        poses_by_key, _, _ = poses_after_alignment(recons, aligned)
        out["mcd"][name] = mcd(fuse_trips(recons, poses_by_key, aligned.match_pairs).features, poses_by_key)
        out["ate_rmse_m"][name] = ate_rmse_m(poses_by_key, truth)
    on_truth = _true_pose_recons(recons, frame, truth, _true_pose_cache(cache_dir, scenario_dir))
    out["mcd"]["true_poses"] = mcd(fuse_trips(on_truth, truth).features, truth)
    out["mcd_true_poses_overlaid"] = mcd(
        [MapFeature(i.type, i.points_xy_world, i.style) for r in on_truth for i in r.instances], truth
    )
    return out


def _evaluate(job: Job) -> dict:
    """One scenario (a worker process)."""
    cache = _true_pose_cache(job.cache_dir, job.scenario_dir)
    cached = cache is not None and cache.exists()
    r = scenario_budget(job.scenario_dir, job.cache_dir)
    return {"spec": job.spec.name, "world": job.spec.world, "seed": job.spec.seed, "cached": cached, **r}


def run_budget_bench(
    scenario_cache: Path,
    work_dir: Path,
    set_name: str = "standard-seeds",
    jobs: int = 2,
    progress: Callable[[str], None] | None = None,
) -> list[dict]:
    """Every scenario of ``set_name`` (simulated unless cached in ``scenario_cache``; single-trip
    results cached in ``work_dir``, keyed by ``CACHE_SOURCES``) in ``jobs`` processes."""
    fingerprint = simulator_fingerprint()
    cache_dir = work_dir / sources_fingerprint(*CACHE_SOURCES)
    work = []
    for spec in scenario_set(set_name):
        if progress:
            progress(f"scenario {spec.name}")
        work.append(Job(spec, ensure_scenario(spec, scenario_cache, fingerprint), cache_dir))
    return map_in_processes(_evaluate, work, jobs, progress, label=lambda r: r["spec"])


def per_world(results: Sequence[dict]) -> dict[str, dict]:
    """World -> the means over its scenarios of every figure (``"n"``: how many)."""
    worlds: dict[str, list[dict]] = {}
    for r in results:
        worlds.setdefault(r["world"], []).append(r)
    return {
        w: {
            "n": len(rs),
            "trips_per_place": float(np.median([r["trips_per_place"] for r in rs])),
            "mcd": {p: float(np.mean([r["mcd"][p] for r in rs])) for p in POSES},
            "mcd_true_poses_overlaid": float(np.mean([r["mcd_true_poses_overlaid"] for r in rs])),
            "ate_rmse_m": {p: float(np.mean([r["ate_rmse_m"][p] for r in rs])) for p in POSES[:2]},
        }
        for w, rs in worlds.items()
    }


def plot_budget(results: Sequence[dict], path: Path, set_name: str = "standard-seeds") -> Path:
    """Bars per world: the mCD on each of the three poses, with the mCD target."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    worlds = per_world(results)
    names = list(worlds)
    fig, ax = plt.subplots(figsize=(1.6 * len(names) + 2.5, 4.2))
    width = 0.26
    labels = {
        "pipeline": "pipeline",
        "exact_registrations": "exact registrations (GNSS floor)",
        "true_poses": "true poses (element stages alone)",
    }
    for k, p in enumerate(POSES):
        ax.bar(
            np.arange(len(names)) + (k - 1) * width,
            [worlds[w]["mcd"][p] for w in names],
            width,
            label=labels[p],
        )
    ax.axhline(MCD_TARGET_M, color="black", lw=1, ls="--", label=f"target {MCD_TARGET_M} m")
    ax.set_xticks(np.arange(len(names)), names)
    ax.set_ylabel("mCD [m] (mean over seeds)")
    ax.set_title(f"Where the map's error comes from (set {set_name})")
    ax.legend(fontsize=8, loc="upper left")
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=90)
    plt.close(fig)
    return path


def render_section(
    results: Sequence[dict],
    figure: Path | None,
    doc_dir: Path,
    elapsed_s: float,
    set_name: str = "standard-seeds",
) -> str:
    """The markdown of BENCHMARKS.md's error-budget section."""
    worlds = per_world(results)
    mean = {p: float(np.mean([r["mcd"][p] for r in results])) for p in POSES}
    regenerate = "csr bench-budget --write BENCHMARKS.md" + (
        "" if set_name == "standard-seeds" else f" --set {set_name}"
    )
    n_cached = sum(bool(r.get("cached")) for r in results)
    cached = (
        f", {n_cached} of {len(results)} scenarios' single-trip results from the cache" if n_cached else ""
    )
    lines = [
        "## Where the map's error comes from (the mCD, `csr bench-budget"
        + ("`)" if set_name == "standard-seeds" else f" --set {set_name}`)"),
        "",
        f"Regenerate: `{regenerate}` ({duration_text(elapsed_s)} on this machine{cached}; scenarios cached in "
        f"`bench-out/scenarios`). Measured {time.strftime('%Y-%m-%d %H:%M UTC', time.gmtime())}. Set `{set_name}` "
        f"({len(results)} scenarios, simulator sources fingerprint `{simulator_fingerprint()}`). Each scenario's trips "
        "are fused as `csr reconstruct` fuses them (`pipeline.fuse_trips`) on three sets of poses: the *pipeline*'s "
        "(single-trip stage, `align_trips`); the same alignment with every accepted sub-map registration replaced by "
        "the true relative pose (*exact registrations*, `python -m csr_core.alignment.evaluate_floor`: what is left is "
        "the trips' GNSS error that the pose graph averages); and the *true poses* in place of the smoothing, the "
        "element stages unchanged (`python -m csr_core.topology.evaluate DIR --poses truth`). Scored as contract "
        "section 6 scores `csr reconstruct` (one rigid SE(2) onto the truth).",
        "",
        f"**Mean mCD over the set: pipeline {mean['pipeline']:.3f} m, exact registrations "
        f"{mean['exact_registrations']:.3f} m, true poses {mean['true_poses']:.3f} m; the target "
        f"{MCD_TARGET_M} m.**",
        "",
    ]
    rows = [
        [
            w,
            str(v["n"]),
            f"{v['trips_per_place']:g}",
            f"{v['mcd']['pipeline']:.3f}",
            f"{v['mcd']['exact_registrations']:.3f}",
            f"{v['mcd']['true_poses']:.3f}",
            f"{v['mcd_true_poses_overlaid']:.3f}",
            f"{v['ate_rmse_m']['pipeline']:.3f}",
            f"{v['ate_rmse_m']['exact_registrations']:.3f}",
        ]
        for w, v in worlds.items()
    ]
    header = [
        "world",
        "scenarios",
        "trips/place",
        "mCD pipeline",
        "mCD exact registrations",
        "mCD true poses",
        "true poses, instances overlaid",
        "ATE pipeline",
        "ATE exact registrations",
    ]
    lines += [
        markdown_table(header, rows),
        "",
        "Per scenario:",
        "",
        markdown_table(
            ["scenario"] + header[2:],
            [
                [
                    r["spec"],
                    f"{r['trips_per_place']:g}",
                    f"{r['mcd']['pipeline']:.3f}",
                    f"{r['mcd']['exact_registrations']:.3f}",
                    f"{r['mcd']['true_poses']:.3f}",
                    f"{r['mcd_true_poses_overlaid']:.3f}",
                    f"{r['ate_rmse_m']['pipeline']:.3f}",
                    f"{r['ate_rmse_m']['exact_registrations']:.3f}",
                ]
                for r in results
            ],
        ),
        "",
    ]
    if figure is not None:
        rel = Path(os.path.relpath(Path(figure).resolve(), doc_dir.resolve()))
        lines += [
            f"![mCD per world on the pipeline's poses, exact registrations and the true poses]({rel.as_posix()})",
            "",
        ]
    lines += [
        "*trips/place*: how many trips drive each place (`bench.evaluate.trips_per_place`; per world the "
        "median over its scenarios). *instances overlaid*: the single-trip instances of every trip on the true poses, not fused: what "
        "fusion gains over them. The *pipeline* columns are this module's own run of `csr reconstruct`'s "
        "stages (`pipeline.poses_after_alignment`, `pipeline.fuse_trips`): on `standard-seeds` they equal "
        "`csr bench`'s pipeline figures (mCD and ATE of all 15 scenarios to the third decimal, checked when "
        "this section was added)."
    ]
    return "\n".join(lines)
