"""The single-trip benchmark: single-trip reconstruction (III-C) on the benchmark's fleets.

``csr bench-single-trip`` runs :func:`csr_core.single_trip.evaluate.evaluate_loaded` on every
scenario of the ``standard-seeds`` set (the five worlds, 10 trips x 1.5 km, seeds 1-3), with the
trips' own smoothed poses and again with their true poses (the element stages alone), and on the
``hard`` set (GNSS jumps and outages) for the jump target. This module holds the targets, the
run, the tables and the figure; the command (``services/cli/bench_single_trip.py``) writes them.
"""

from __future__ import annotations

import math
import os
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from csr_core.bench.runner import (
    ensure_scenario,
    map_in_processes,
    reference_cpu_seconds,
    simulator_fingerprint,
)
from csr_core.bench.sets import WORLDS, ScenarioSpec, scenario_set
from csr_core.bench.tables import duration_text, markdown_table

SECTION = "single-trip"
SETS = ("standard-seeds", "hard")

# the single-trip targets
RPE_RATIO_MAX = 1.0 / 3.0  # smoothed RPE (10 m) / raw GNSS RPE
JUMP_ERROR_MAX_M = 3.0  # hard: smoothed error where raw GNSS is > 5 m off
CORRECTNESS_MIN = 0.97  # trip-level instances after the trip's rigid offset, at 0.5 m
COMPLETENESS_MIN = 0.90
SECONDS_PER_KM_MAX = 0.5  # one core, the whole stage


@dataclass(frozen=True, slots=True)
class Job:
    spec: ScenarioSpec
    scenario_dir: Path
    true_poses_too: bool


def _evaluate(job: Job) -> list[dict]:
    """One scenario, loaded once: smoothed poses, and true poses when asked (a worker process)."""
    from csr_core.single_trip.evaluate import evaluate_loaded, load_scenario

    loaded = load_scenario(job.scenario_dir)
    variants = (False, True) if job.true_poses_too else (False,)
    out = []
    for true_poses in variants:
        result = evaluate_loaded(loaded, true_poses=true_poses)
        out.append(
            result
            | {
                "world": job.spec.world,
                "profile": job.spec.profile,
                "seed": job.spec.seed,
                "spec": job.spec.name,
            }
        )
    return out


def run_single_trip_bench(
    cache_dir: Path, sets: Sequence[str] = SETS, jobs: int = 2, progress: Callable[[str], None] | None = None
) -> list[dict]:
    """Every scenario of ``sets`` (simulated unless cached in ``cache_dir``), evaluated in
    ``jobs`` processes. One dict per scenario and pose source (``true_poses`` False / True); the
    ``hard`` set's scenarios only with their smoothed poses (they are there for the jumps)."""
    fingerprint = simulator_fingerprint()
    reference_s = reference_cpu_seconds()
    work = []
    for set_name in sets:
        for spec in scenario_set(set_name):
            if progress:
                progress(f"scenario {spec.name}")
            work.append(Job(spec, ensure_scenario(spec, cache_dir, fingerprint), spec.profile != "hard"))
    batches = map_in_processes(_evaluate, work, jobs, progress, label=lambda batch: batch[0]["spec"])
    return [r | {"machine_reference_s": reference_s} for batch in batches for r in batch]


def _mean(values: Sequence[float]) -> float:
    finite = [v for v in values if v is not None and math.isfinite(v)]
    return float(np.mean(finite)) if finite else float("nan")


def _mark(ok: bool) -> str:
    return "yes" if ok else "**no**"


def _fmt(v: float, digits: int = 3) -> str:
    return "" if v is None or not math.isfinite(v) else f"{v:.{digits}f}"


def _world_order(world: str) -> int:
    return WORLDS.index(world) if world in WORLDS else len(WORLDS)


def by_world(results: Sequence[dict], true_poses: bool = False) -> dict[str, list[dict]]:
    """The target scenarios (every profile but ``hard``) per world, in the benchmark's order."""
    out: dict[str, list[dict]] = {}
    for r in results:
        if r["profile"] != "hard" and r["true_poses"] == true_poses:
            out.setdefault(r["world"], []).append(r)
    return dict(sorted(out.items(), key=lambda item: _world_order(item[0])))


def world_summary(results: Sequence[dict]) -> list[dict]:
    """Per world (the target scenarios), means over its seeds, and whether each target is met on
    every seed."""
    truth = by_world(results, true_poses=True)
    rows = []
    for world, rs in by_world(results).items():
        ratio = [r["rpe_smoothed_m"] / r["rpe_raw_gnss_m"] for r in rs]
        rows.append(
            {
                "world": world,
                "rpe_ratio": _mean(ratio),
                "rpe_ok": all(x <= RPE_RATIO_MAX for x in ratio),
                "ate_smoothed_m": _mean([r["ate_smoothed_m"] for r in rs]),
                "ate_raw_gnss_m": _mean([r["ate_raw_gnss_m"] for r in rs]),
                "ate_ok": all(r["ate_smoothed_m"] <= r["ate_raw_gnss_m"] for r in rs),
                **{
                    f"{kind}_{m}": _mean([r[kind][m] for r in rs])
                    for kind in ("rigid", "local")
                    for m in ("correctness", "completeness")
                },
                **{
                    f"{kind}_min_{m}": min(r[kind][m] for r in rs)
                    for kind in ("rigid", "local")
                    for m in ("correctness", "completeness")
                },
                "rigid_ok": all(
                    r["rigid"]["correctness"] >= CORRECTNESS_MIN
                    and r["rigid"]["completeness"] >= COMPLETENESS_MIN
                    for r in rs
                ),
                "local_ok": all(
                    r["local"]["correctness"] >= CORRECTNESS_MIN
                    and r["local"]["completeness"] >= COMPLETENESS_MIN
                    for r in rs
                ),
                "true_correctness": _mean([r["rigid"]["correctness"] for r in truth.get(world, [])]),
                "true_completeness": _mean([r["rigid"]["completeness"] for r in truth.get(world, [])]),
                "seconds_per_km": _mean([r["seconds_per_km"] for r in rs]),
                "speed_ok": all(r["seconds_per_km"] <= SECONDS_PER_KM_MAX for r in rs),
                "stage_seconds_per_km": {
                    stage: _mean([r["stage_seconds_per_km"].get(stage, float("nan")) for r in rs])
                    for stage in _stages(rs)
                },
            }
        )
    return rows


def _stages(results: Sequence[dict]) -> list[str]:
    """The stages the results time (``single_trip.STAGES``, in its order), none for older results."""
    for r in results:
        if r.get("stage_seconds_per_km"):
            return list(r["stage_seconds_per_km"])
    return []


def _machine_note(results: Sequence[dict]) -> str:
    """The machine reference the CPU figures were measured beside (``runner.reference_cpu_seconds``)."""
    refs = [r["machine_reference_s"] for r in results if "machine_reference_s" in r]
    if not refs:
        return "Machine reference not measured."
    return (
        f"Machine reference: {float(np.median(refs)):.3f} CPU s for the fixed Python and numpy workload of "
        "`runner.reference_cpu_seconds`, measured before the run: the CPU columns scale with it from one "
        "machine to the next."
    )


def render_section(
    results: Sequence[dict], figure: Path | None, doc_dir: Path, elapsed_s: float, sets: Sequence[str] = SETS
) -> str:
    """The markdown of BENCHMARKS.md's single-trip section."""
    summary = world_summary(results)
    hard = [r for r in results if r["profile"] == "hard"]
    target_specs = sorted({r["spec"] for r in results if r["profile"] != "hard"})
    regenerate = "csr bench-single-trip --write BENCHMARKS.md" + (
        "" if tuple(sets) == SETS else f" --sets {','.join(sets)}"
    )
    lines = [
        "## Single-trip reconstruction (`csr bench-single-trip`)",
        "",
        f"Regenerate: `{regenerate}` ({duration_text(elapsed_s)} on this machine; scenarios cached in "
        f"`bench-out/scenarios`). Measured {time.strftime('%Y-%m-%d %H:%M UTC', time.gmtime())}. "
        f"Sets {', '.join(f'`{s}`' for s in sets)} ({len(target_specs)} target scenarios: "
        f"{', '.join(f'`{n}`' for n in target_specs)}{'; the `hard` set for the GNSS jumps' if hard else ''}), simulator sources "
        f"fingerprint `{simulator_fingerprint()}`. Every trip goes through `reconstruct_trip` alone (no other "
        "trip, no alignment) and is scored against its own truth (`csr_core/single_trip/evaluate.py`): poses "
        "as contract section 6 (no global alignment); instances with the contract's map metric (0.5 m samples "
        "and threshold) against the truth within 15 m of the trip's true path, pooled over the trip's types.",
        "",
        "### Targets per world (means over the seeds; met = on every seed)",
        "",
    ]
    header = [
        "world",
        "RPE smoothed / raw",
        "<= 1/3",
        "ATE smoothed / raw [m]",
        "no worse",
        "instances, rigid: correct. / compl.",
        ">= 0.97 / 0.90",
        "local 100 m",
        "met",
        "true poses",
        "CPU s/km",
        "< 0.5",
    ]
    rows = [
        [
            s["world"],
            _fmt(s["rpe_ratio"], 3),
            _mark(s["rpe_ok"]),
            f"{_fmt(s['ate_smoothed_m'])} / {_fmt(s['ate_raw_gnss_m'])}",
            _mark(s["ate_ok"]),
            f"{_fmt(s['rigid_correctness'])} / {_fmt(s['rigid_completeness'])} (worst {_fmt(s['rigid_min_correctness'])} "
            f"/ {_fmt(s['rigid_min_completeness'])})",
            _mark(s["rigid_ok"]),
            f"{_fmt(s['local_correctness'])} / {_fmt(s['local_completeness'])}",
            _mark(s["local_ok"]),
            f"{_fmt(s['true_correctness'])} / {_fmt(s['true_completeness'])}",
            _fmt(s["seconds_per_km"], 2),
            _mark(s["speed_ok"]),
        ]
        for s in summary
    ]
    lines += [markdown_table(header, rows), ""]
    lines += [
        "- *rigid* is the targets' figure: each trip's instances moved by the trip's own rigid offset (SE(2) of its "
        "smoothed onto its true positions). *local 100 m*: each instance moved by the offset of the poses over "
        "the 100 m of travel around it instead (about one sub-map, the unit III-D aligns). *true poses*: the "
        "pose smoothing replaced by the true poses, so the figure is the element stages' alone (tracking, "
        "splicing, ghost and false-positive rejection).",
        "- The gap between *rigid* and *local* is the GNSS error that changes within one trip (a bias with "
        "tens of seconds to minutes of correlation time): one trip's GNSS and odometry cannot see it, its "
        "size is the trip-aligned ATE below. The multi-trip alignment removes it sub-map by sub-map.",
        "",
        "### Where the CPU goes (s/km per stage, smoothed poses, means over the seeds)",
        "",
        markdown_table(
            ["world", *_stages(results), "all"],
            [
                [
                    s["world"],
                    *(
                        _fmt(s["stage_seconds_per_km"].get(stage, float("nan")), 3)
                        for stage in _stages(results)
                    ),
                    _fmt(s["seconds_per_km"], 3),
                ]
                for s in summary
            ],
        ),
        "",
        f'{_machine_note(results)} Stages as `reconstruct_trip` reports them (`diagnostics["cpu_seconds"]`): '
        "poses = Eq. 2's smoothing (its LM solves are most of it), tracking = keyframes, tracking and dash "
        "chaining, splicing = every track spliced and tested (ghosts, false positives, crossings), "
        "unseen_cut = the paint-break and unseen cuts, noise = the noise estimate and the mixture test.",
        "",
        "### Hard profile: GNSS jumps",
        "",
    ]
    jump_rows = [
        [
            r["spec"],
            str(r["trips"]),
            str(r["jump_frames"]),
            _fmt(r["jump_max_smoothed_err_m"], 2),
            _mark(not (r["jump_max_smoothed_err_m"] > JUMP_ERROR_MAX_M)),
            _fmt(r["ate_raw_gnss_m"]),
            _fmt(r["ate_smoothed_m"]),
        ]
        for r in hard
    ]
    lines += [
        markdown_table(
            [
                "scenario",
                "trips",
                "frames with raw GNSS > 5 m off",
                "worst smoothed error there [m]",
                "<= 3 m",
                "ATE raw [m]",
                "ATE smoothed [m]",
            ],
            jump_rows,
        )
        if hard
        else "(`hard` not run)",
        "",
    ]
    lines += ["### Noise estimates: lateral sigma per type, estimated / observed [m]", ""]
    noise_types = ("lane_divider", "road_boundary", "centerline")
    noise_rows = []
    for world, rs in by_world(results, true_poses=True).items():
        cells = []
        for t in noise_types:
            est = _mean([r["noise"][t]["estimated_lateral_sigma_m"] for r in rs if t in r.get("noise", {})])
            obs = _mean([r["noise"][t]["observed_lateral_sigma_m"] for r in rs if t in r.get("noise", {})])
            cells.append(f"{_fmt(est)} / {_fmt(obs)}" if math.isfinite(est) else "")
        noise_rows.append([world, *cells])
    lines += [
        markdown_table(["world", *noise_types], noise_rows) if noise_rows else "(no true-pose runs)",
        "",
    ]
    lines += [
        "With the true poses, so that a point's error is the perception's alone. *Estimated*: what the "
        "stage reports with the trip (`TripReconstruction.noise`, mean over trips and seeds), the sigma "
        "that sets Eq. 3's thresholds and Eq. 5-6's widths. *Observed*: 1.4826 x the median distance of "
        "the trips' detected points to the truth of their type (points 1 m or more away left out: ghosts, "
        "false positives). The estimate comes from residuals to the trip's own instance, so it cannot "
        "contain the part of an element's error that stays the same through all the frames of a trip; "
        "it is expected a little lower. Along-track sigmas are not compared (no point-wise truth).",
        "",
    ]
    lines += ["### Per scenario", ""]
    per_rows = []
    for r in sorted(
        results, key=lambda r: (r["profile"] == "hard", r["seed"], _world_order(r["world"]), r["true_poses"])
    ):
        per_rows.append(
            [
                r["spec"],
                "true" if r["true_poses"] else "smoothed",
                f"{r['km']:.1f}",
                _fmt(r["ate_raw_gnss_m"]),
                _fmt(r["ate_smoothed_m"]),
                _fmt(r["ate_trip_aligned_m"]),
                _fmt(r["rpe_raw_gnss_m"]),
                _fmt(r["rpe_smoothed_m"]),
                f"{_fmt(r['rigid']['correctness'])} / {_fmt(r['rigid']['completeness'])}",
                f"{_fmt(r['local']['correctness'])} / {_fmt(r['local']['completeness'])}",
                _fmt(r["seconds_per_km"], 2),
            ]
        )
    lines += [
        markdown_table(
            [
                "scenario",
                "poses",
                "km",
                "ATE raw",
                "ATE smoothed",
                "ATE trip-aligned",
                "RPE raw",
                "RPE smoothed",
                "rigid correct. / compl.",
                "local 100 m",
                "CPU s/km",
            ],
            per_rows,
        ),
        "",
    ]
    lines += [
        "Pose columns in metres; with true poses they are zero by construction. CPU s/km is "
        "`time.process_time` of `reconstruct_trip` (one core) per km of trip, on a shared machine."
    ]
    if figure is not None:
        rel = Path(os.path.relpath(Path(figure).resolve(), doc_dir.resolve())) if doc_dir else Path(figure)
        lines += ["", f"![Trip-level instances by world and offset model]({rel.as_posix()})"]
    return "\n".join(lines)


def plot_instances_by_world(results: Sequence[dict], path: Path) -> Path:
    """Correctness and completeness per world under the three offset models, targets dashed."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    summary = world_summary(results)
    worlds = [s["world"] for s in summary]
    x = np.arange(len(worlds))
    fig, axes = plt.subplots(1, 2, figsize=(11, 3.8), sharey=True)
    for ax, metric, target in (
        (axes[0], "correctness", CORRECTNESS_MIN),
        (axes[1], "completeness", COMPLETENESS_MIN),
    ):
        for k, (label, key) in enumerate(
            (
                ("rigid (target)", f"rigid_{metric}"),
                ("local 100 m", f"local_{metric}"),
                ("true poses", f"true_{metric}"),
            )
        ):
            ax.bar(x + (k - 1) * 0.27, [s[key] for s in summary], 0.27, label=label)
        ax.axhline(target, color="k", ls="--", lw=1)
        ax.set_xticks(x, worlds)
        ax.set_title(f"trip-level {metric} at 0.5 m (target {target:g})")
        ax.set_ylim(0.8, 1.0)
        ax.grid(axis="y", alpha=0.3)
    axes[0].legend(loc="lower left", fontsize=8)
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path
