"""Incremental against batch map building on a scenario folder (contract section 5).

    python -m csr_core.topology.evaluate_incremental SCENARIO_DIR [--start 5] [--cache FILE]

The trips' aligned instances (``evaluate.trip_instances``, ``--poses aligned``) are fused once
in a batch (``generate_topology`` over all trips) and once incrementally: ``generate_topology``
over the first ``--start`` trips (by key), then ``update_topology`` with one trip at a time.
Both maps are scored as contract section 6 (after the global alignment of the poses), with the
time of each incremental update: the cost of one more trip must not grow with the map's trips.
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np

from csr_core import metrics
from csr_core.scenario import geo_features_to_local, read_map_geojson, read_scenario_meta
from csr_core.topology import TopologyResult, generate_topology, update_topology
from csr_core.topology.evaluate import cached_trip_instances


def _inputs(data: dict, keys: list[str]) -> dict:
    return {
        "instances_per_trip": {k: data[k][0] for k in keys},
        "noise_per_trip": {k: data[k][1] for k in keys},
        "trip_times": {k: data[k][4] for k in keys},
        "paths_xy_per_trip": {k: data[k][2][:, :2] for k in keys},
    }


def compare(scenario_dir: str | Path, start: int = 5, cache: str | None = None) -> dict:
    scenario_dir = Path(scenario_dir)
    data, _ = cached_trip_instances(scenario_dir, "aligned", cache)
    keys = sorted(data)
    if not 1 <= start < len(keys):
        raise SystemExit(
            f"--start must be between 1 and {len(keys) - 1} (the scenario has {len(keys)} trips)"
        )
    meta = read_scenario_meta(scenario_dir)
    truth = geo_features_to_local(read_map_geojson(scenario_dir / "truth" / "map.geojson"), meta.frame)
    true_xy = np.concatenate([data[k][3][:, :2] for k in keys])
    truth_T_est = metrics.umeyama_se2(np.concatenate([data[k][2][:, :2] for k in keys]), true_xy)

    def score(result: TopologyResult) -> dict:
        ms = metrics.map_scores(metrics.transform_features(truth_T_est, result.features), truth, true_xy)
        return {
            "mcd": round(ms.mcd, 4),
            "features": len(result.features),
            **{
                t.value: {
                    "cd": round(s.cd, 4),
                    "completeness": round(s.completeness, 3),
                    "correctness": round(s.correctness, 3),
                }
                for t, s in ms.per_type.items()
                if np.isfinite(s.cd)
            },
        }

    t0 = time.perf_counter()
    batch = generate_topology(**_inputs(data, keys))
    batch_s = time.perf_counter() - t0
    state = generate_topology(**_inputs(data, keys[:start]))
    seconds = []
    for k in keys[start:]:
        t1 = time.perf_counter()
        one = _inputs(data, [k])
        state = update_topology(
            state,
            one["instances_per_trip"],
            one["noise_per_trip"],
            trip_times=one["trip_times"],
            paths_xy_per_trip=one["paths_xy_per_trip"],
        )
        seconds.append(time.perf_counter() - t1)
    return {
        "scenario": meta.name,
        "trips": len(keys),
        "start": start,
        "batch": {**score(batch), "seconds": round(batch_s, 2)},
        "incremental": {
            **score(state),
            "update_seconds_first5": [round(s, 3) for s in seconds[:5]],
            "update_seconds_last5": [round(s, 3) for s in seconds[-5:]],
        },
    }


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("scenario")
    ap.add_argument(
        "--start", type=int, default=5, help="trips fused in a batch before the one-by-one updates"
    )
    ap.add_argument("--cache", help="pickle of the trips' aligned instances (written if missing)")
    args = ap.parse_args(argv)
    print(json.dumps(compare(args.scenario, args.start, args.cache), indent=2))  # noqa: T201
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
