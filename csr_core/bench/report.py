"""The bench section of BENCHMARKS.md (between ``<!-- bench:begin -->`` and ``<!-- bench:end -->``)."""

from __future__ import annotations

import os
from collections.abc import Sequence
from datetime import UTC, datetime
from pathlib import Path

from csr_core.bench.runner import Record
from csr_core.bench.sets import scenario_set
from csr_core.bench.tables import table_ablation, table_cost, table_map, table_per_world, table_pose


def _rel(path: Path, base: Path) -> str:
    return os.path.relpath(path.resolve(), base.resolve())


def render_section(
    records: Sequence[Record],
    set_name: str,
    figures: Sequence[tuple[str, Path]],
    doc_dir: Path,
    elapsed_s: float,
    run_s: float | None = None,
) -> str:
    specs = scenario_set(set_name)
    fingerprints = sorted(
        {r.scenario_dir.name.split("-sim")[-1] for r in records if "-sim" in r.scenario_dir.name}
    )
    scen = ", ".join(f"`{s.name}`" for s in specs)
    failed = [r for r in records if not r.ok]
    pipeline_stages = next(
        (r.report.get("diagnostics", {}).get("stages") for r in records if r.method == "pipeline" and r.ok),
        None,
    )
    ablation = table_ablation(records)
    parts = [
        f"## Accuracy and cost benchmark (`csr bench --set {set_name}`)",
        "",
        f"Regenerate: `csr bench --set {set_name} --write BENCHMARKS.md` "
        f"(~{(run_s if run_s is not None else elapsed_s) / 60:.0f} min of `csr reconstruct` runs plus simulation "
        "and evaluation on this machine; scenarios are cached in `bench-out/scenarios`). "
        f"Measured {datetime.now(UTC):%Y-%m-%d %H:%M} UTC.",
        "",
        f"Set `{set_name}`: {scen} (world-profile-trips x trip length-seed, simulated by `csr simulate`; "
        f"simulator sources fingerprint `{', '.join(fingerprints) or 'none (hand-made toy)'}`). "
        "Every method runs as `csr reconstruct SCENARIO --out OUT --method M` in a subprocess and its "
        "`OUT` folder is scored exactly as contract section 6 says (`csr_core/metrics.py`). Summary rows are "
        "means over the scenarios; per-scenario rows below.",
        "",
        "Methods:",
        "",
        f"- **CSR pipeline**: `csr reconstruct` default. Stages in this build: `{pipeline_stages}`."
        + (
            " Until the single-trip and alignment stages are wired in, it equals the GNSS-only baseline."
            if pipeline_stages == ["gnss_poses", "naive_fusion"]
            else ""
        ),
        "- **GNSS-only**: raw GNSS poses (outages bridged by odometry, yaw from the GNSS course), every "
        "perceived element placed with them and fused naively (`csr_core/baselines/naive_fusion.py`: each "
        "5 m keyframe keeps the strip of its perception just ahead of the car, strips chained per on-vehicle "
        "track; no merging across trips).",
        "- **RoadMap-style (ICP)**: GNSS placement, then each trip's semantic points, in 75 m chunks, "
        "registered to the map accumulated from earlier trips by point-to-point ICP from **small_gicp** "
        "(maintained, light numpy-only wheel, by the author of interactive_slam; Open3D would add several hundred MB for "
        "the same ICP). Element types are kept apart by giving each its own height. Chunk corrections are "
        "interpolated along the trip; finally all trips are moved together to their mean GNSS placement "
        "(chained registration otherwise inherits the first trip's GNSS error); same naive fusion.",
        "",
        "Because the baselines keep one copy of an element per trip, truth-side distances see the nearest "
        "copy (completeness is optimistic) while every copy counts on the predicted side (correctness).",
        "",
        "### Map accuracy (Table II), after the global alignment [m]",
        "",
        table_map(records, aligned=True),
        "",
        "Completeness and correctness (share of samples within 0.5 m) are means over lane dividers, "
        "centerlines and road boundaries. Raw (no global alignment):",
        "",
        table_map(records, aligned=False),
        "",
        "### Pose accuracy (Table III) [m]",
        "",
        table_pose(records),
        "",
        "RPE pairs each frame with the first later frame >= 10 m of true travel away (contract section 6); "
        "ATE and RPE are cross-checked against evo in `tests/unit/test_metrics.py`.",
        "",
        "### Cost (Table IV)",
        "",
        table_cost(records),
        "",
        "Wall time is the whole `csr reconstruct` command (Python start, gunzip + validation of the uploads, "
        "reconstruction, writing) per km of uploaded trip length (true path length); processing is the "
        "reconstruction call alone. Uploaded = the trip bodies as sent (gzip). Output = what the pipeline "
        "produces (poses CSVs + map.geojson). Stored = uploaded + output (what the service keeps per km). "
        "Peak memory is the `csr reconstruct` process's max RSS (`wait4` rusage). The machine (2 cores) was shared "
        "with other jobs while measuring: identical runs "
        "took up to 4x different wall times, so read the time columns as orders of magnitude.",
        "",
        "### Ablation (Table I), pipeline RPE after the global alignment [m]",
        "",
        ablation
        if ablation
        else (
            "Not run for this set (`csr bench --no-ablation`): the `standard-seeds` section has it."
            if pipeline_stages and {"coarse", "fine"} <= set(pipeline_stages)
            else "Not measured yet: the pipeline has no coarse/fine alignment stages in this build "
            f"(stages: `{pipeline_stages}`). `csr bench` runs `--no-fine` (coarse only) and `--no-coarse` "
            "(fine only) automatically as soon as the pipeline reports both stages."
        ),
        "",
        "### Per scenario (aligned)",
        "",
        table_per_world(records),
        "",
    ]
    if failed:
        parts += [
            "Failed runs: " + "; ".join(f"{r.scenario} {r.method}: {r.run.stderr_tail}" for r in failed),
            "",
        ]
    if figures:
        parts += ["### Figures", ""]
        for caption, path in figures:
            parts += [f"{caption}:", "", f"![{caption}]({_rel(path, doc_dir)})", ""]
    return "\n".join(parts)
