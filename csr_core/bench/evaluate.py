"""Evaluate a ``csr reconstruct`` output folder against its scenario's truth (contract section 6).

Reads ``SCENARIO/truth`` and ``OUT_DIR`` (poses CSVs, map.geojson), projects everything into the
scenario's local tmerc plane (centred on ``scenario.json``'s origin) and calls
:func:`csr_core.metrics.evaluate`. Output rows are matched to truth rows by index (one row per
uploaded frame, upload order); their timestamps must agree.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
from scipy.spatial import cKDTree

from csr_core.errors import ScenarioError
from csr_core.metrics import Evaluation, evaluate
from csr_core.scenario import (
    ScenarioMeta,
    geo_features_to_local,
    read_map_geojson,
    read_poses_dir,
    read_scenario_meta,
)
from csr_core.types import MapFeature


@dataclass(frozen=True, slots=True)
class EvaluatedOutput:
    meta: ScenarioMeta
    evaluation: Evaluation
    true_xy_by_key: dict[str, np.ndarray]
    est_xy_by_key: dict[str, np.ndarray]
    truth_map: tuple[MapFeature, ...]
    pred_map: tuple[MapFeature, ...]
    trip_length_km: float
    trips_per_place: float = float("nan")  # median over frames, :func:`trips_per_place`


def evaluate_output(scenario_dir: str | Path, out_dir: str | Path) -> EvaluatedOutput:
    scenario_dir, out_dir = Path(scenario_dir), Path(out_dir)
    meta = read_scenario_meta(scenario_dir)
    frame = meta.frame
    truth_tracks = read_poses_dir(scenario_dir / "truth" / "poses")
    if not truth_tracks:
        raise ScenarioError(f"no truth poses in {scenario_dir / 'truth' / 'poses'}")
    est_tracks = read_poses_dir(out_dir / "poses") if (out_dir / "poses").is_dir() else {}
    unknown = sorted(set(est_tracks) - set(truth_tracks))
    if unknown:
        raise ScenarioError(f"{out_dir / 'poses'}: poses for trips not in the scenario: {unknown[:3]}")
    true_xy = {k: frame.to_local(t.lonlat_deg) for k, t in truth_tracks.items()}
    est_xy = {}
    for k, t in est_tracks.items():
        truth_t = truth_tracks[k].timestamps_s
        if len(t.timestamps_s) != len(truth_t) or not np.allclose(t.timestamps_s, truth_t, atol=2e-3):
            raise ScenarioError(
                f"{out_dir / 'poses' / (k + '.csv')}: rows do not match the uploaded frames "
                f"({len(t.timestamps_s)} rows, {len(truth_t)} frames)"
            )
        est_xy[k] = frame.to_local(t.lonlat_deg)
    truth_map = geo_features_to_local(read_map_geojson(scenario_dir / "truth" / "map.geojson"), frame)
    pred_map = geo_features_to_local(read_map_geojson(out_dir / "map.geojson"), frame)
    length_km = (
        sum(float(np.linalg.norm(np.diff(xy, axis=0), axis=1).sum()) for xy in true_xy.values()) / 1000.0
    )
    return EvaluatedOutput(
        meta,
        evaluate(true_xy, est_xy, truth_map, pred_map),
        true_xy,
        est_xy,
        truth_map,
        pred_map,
        length_km,
        trips_per_place(true_xy),
    )


#: a trip "drives the same road" as a frame when its true path passes within this distance of it:
#: the two directions of a two-way road and neighbouring lanes, not the next road
SAME_ROAD_RADIUS_M = 8.0


def trips_per_place(
    true_xy_by_key: dict[str, np.ndarray], radius_m: float = SAME_ROAD_RADIUS_M, step: int = 10
) -> float:
    """How many trips drive each place of the fleet: the median, over every ``step``-th true frame
    of every trip, of the number of trips (its own included) whose true path passes within
    ``radius_m``. The alignment's accuracy targets are stated for ">= 10 trips per road"; this is the
    figure to read them against."""
    paths = [xy for xy in true_xy_by_key.values() if len(xy)]
    if not paths:
        return float("nan")
    trees = [cKDTree(xy) for xy in paths]
    counts = []
    for xy in paths:
        probe = xy[::step]
        counts.append(
            sum(
                (tree.query(probe, distance_upper_bound=radius_m)[0] <= radius_m).astype(int)
                for tree in trees
            )
        )
    return float(np.median(np.concatenate(counts)))
