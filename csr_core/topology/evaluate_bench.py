"""Topology generation alone on the benchmark's own inputs, scored as ``csr bench`` scores them.

    python -m csr_core.topology.evaluate_bench SCENARIO_DIR [SCENARIO_DIR ...] --cache-dir DIR

Per scenario, ``csr_core.pipeline.reconstruct`` (what ``csr reconstruct`` runs) is run once up
to its call of ``generate_topology``, whose inputs (aligned instances, noise, trip times, match
pairs, paths) are kept in ``DIR/<scenario>.pkl`` with the world frame and the poses; later runs
read them and redo only topology generation, so a change of fusion is measured in seconds on
exactly the instances the benchmark fuses. The map is carried to the scenario's plane through
lon/lat (as ``map.geojson`` is) and scored with ``csr_core.metrics.evaluate`` (contract
section 6, as ``csr_core/bench/evaluate.py``). Prints per scenario the aligned and raw CD of
every type, mCD and the line types' completeness / correctness, then the means over the
scenarios (CD of a type only over the scenarios that have it, as BENCHMARKS.md does).
"""

from __future__ import annotations

import argparse
import json
import pickle
from pathlib import Path

import numpy as np

from csr_core import metrics
from csr_core.geo import LocalFrame
from csr_core.scenario import (
    geo_features_to_local,
    list_trip_files,
    load_trip,
    read_map_geojson,
    read_poses_dir,
    read_scenario_meta,
)
from csr_core.types import MapFeature

LINE_TYPES = ("lane_divider", "centerline", "road_boundary")


def pipeline_topology_inputs(scenario_dir: Path) -> dict:
    """Run the pipeline on the scenario's trips and keep what it hands to ``generate_topology``."""
    import csr_core.pipeline as pipeline

    captured: dict = {}
    generate = pipeline.generate_topology

    def keep(*args, **kwargs):
        captured["args"], captured["kwargs"] = args, kwargs
        return generate(*args, **kwargs)

    pipeline.generate_topology = keep
    try:
        recon = pipeline.reconstruct([load_trip(f) for f in list_trip_files(scenario_dir)])
    finally:
        pipeline.generate_topology = generate
    return {
        "args": captured["args"],
        "kwargs": captured["kwargs"],
        "origin": (recon.origin_lat, recon.origin_lon),
        "poses": recon.poses_xyyaw_world,
    }


def score_scenario(scenario_dir: Path, inputs: dict) -> dict:
    from csr_core.topology import generate_topology

    meta = read_scenario_meta(scenario_dir)
    truth = read_poses_dir(scenario_dir / "truth" / "poses")
    true_xy = {k: meta.frame.to_local(t.lonlat_deg) for k, t in truth.items()}
    truth_map = geo_features_to_local(read_map_geojson(scenario_dir / "truth" / "map.geojson"), meta.frame)
    world = LocalFrame(*inputs["origin"])
    result = generate_topology(*inputs["args"], **inputs["kwargs"])
    pred = [
        MapFeature(
            f.type,
            meta.frame.to_local(world.to_lonlat(f.points_xy_world)),
            f.style,
            f.feature_id,
            f.properties,
        )
        for f in result.features
    ]
    est = {k: meta.frame.to_local(world.to_lonlat(p[:, :2])) for k, p in inputs["poses"].items()}
    ev = metrics.evaluate(true_xy, est, truth_map, pred)
    out = {}
    for name, ms in (("aligned", ev.map_aligned), ("raw", ev.map_raw)):
        per = {t.value: s for t, s in ms.per_type.items()}
        out[name] = {
            "mcd": ms.mcd,
            **{t: per[t].cd for t in per if np.isfinite(per[t].cd)},
            "completeness": float(np.mean([per[t].completeness for t in LINE_TYPES])),
            "correctness": float(np.mean([per[t].correctness for t in LINE_TYPES])),
        }
    return out


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("scenarios", nargs="+")
    ap.add_argument("--cache-dir", required=True, help="topology inputs per scenario (written if missing)")
    args = ap.parse_args(argv)
    cache_dir = Path(args.cache_dir)
    cache_dir.mkdir(parents=True, exist_ok=True)
    rows = {}
    for scenario in map(Path, args.scenarios):
        cache = cache_dir / f"{scenario.name}.pkl"
        if cache.exists():
            inputs = pickle.loads(cache.read_bytes())
        else:
            inputs = pipeline_topology_inputs(scenario)
            cache.write_bytes(pickle.dumps(inputs))
        rows[scenario.name] = score_scenario(scenario, inputs)
    means = {
        name: {
            key: float(np.nanmean([r[name].get(key, np.nan) for r in rows.values()]))
            for key in sorted({k for r in rows.values() for k in r[name]})
        }
        for name in ("aligned", "raw")
    }
    print(json.dumps({"scenarios": rows, "mean": means}, indent=1))  # noqa: T201
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
