"""Where the map's error comes from (``csr_core.bench.error_budget``, ``csr bench-budget``)."""

from __future__ import annotations

import math
from pathlib import Path

import pytest

from csr_core.bench.error_budget import (
    MCD_TARGET_M,
    POSES,
    per_world,
    plot_budget,
    render_section,
    scenario_budget,
)
from csr_core.sim import simulate_scenario

pytestmark = pytest.mark.unit


def test_a_scenario_fused_on_three_poses_and_the_true_poses_leave_the_least(tmp_path: Path) -> None:
    scenario = tmp_path / "s"
    simulate_scenario("roundabout", 3, "standard", 5, scenario, trip_length_m=400.0)
    cache = tmp_path / "cache"
    r = scenario_budget(scenario, cache)
    assert r["trips"] == 3 and set(r["mcd"]) == set(POSES)
    assert 1.0 <= r["trips_per_place"] <= 3.0
    assert all(0.0 < v < 1.0 for v in r["mcd"].values())
    # the element stages alone leave far less than the GNSS the trips align on (ATE ~0.5 m here)
    assert r["mcd"]["true_poses"] < 0.6 * r["mcd"]["pipeline"]
    assert r["mcd"]["true_poses"] < 0.6 * r["mcd"]["exact_registrations"]
    assert r["ate_rmse_m"]["pipeline"] > 0.1 and r["ate_rmse_m"]["exact_registrations"] > 0.1
    # fused on the true poses is not worse than the same instances overlaid
    assert r["mcd"]["true_poses"] <= r["mcd_true_poses_overlaid"] + 0.005
    # single-trip results (smoothed and on the true poses) are cached and give the same figures again
    assert len(list(cache.glob("*.pkl"))) == 2
    assert scenario_budget(scenario, cache) == r


def _result(spec: str, world: str, pipeline: float, exact: float, true: float) -> dict:
    return {
        "spec": spec,
        "world": world,
        "seed": 1,
        "trips": 10,
        "trips_per_place": 3.0,
        "cached": False,
        "mcd": {"pipeline": pipeline, "exact_registrations": exact, "true_poses": true},
        "mcd_true_poses_overlaid": true + 0.01,
        "ate_rmse_m": {"pipeline": 2 * pipeline, "exact_registrations": 2 * exact},
    }


def test_worlds_are_means_over_their_seeds_and_the_section_names_the_target(tmp_path: Path) -> None:
    results = [
        _result("urban-s1", "urban", 0.06, 0.05, 0.04),
        _result("urban-s2", "urban", 0.08, 0.07, 0.04),
        _result("highway-s1", "highway", 0.12, 0.11, 0.03),
    ]
    worlds = per_world(results)
    assert worlds["urban"]["n"] == 2 and worlds["highway"]["n"] == 1
    assert math.isclose(worlds["urban"]["mcd"]["pipeline"], 0.07)
    assert math.isclose(worlds["urban"]["ate_rmse_m"]["exact_registrations"], 0.12)
    figure = plot_budget(results, tmp_path / "figures" / "budget.png")
    assert figure.stat().st_size > 10_000
    text = render_section(results, figure, tmp_path, 75.0)
    mean_pipeline = (0.06 + 0.08 + 0.12) / 3
    assert f"pipeline {mean_pipeline:.3f} m" in text and f"target {MCD_TARGET_M} m" in text
    assert "| urban | 2 | 3 | 0.070 | 0.060 | 0.040 | 0.050 | 0.140 | 0.120 |" in text
    assert "| highway-s1 | 3 | 0.120 | 0.110 | 0.030 |" in text
    assert "](figures/budget.png)" in text
