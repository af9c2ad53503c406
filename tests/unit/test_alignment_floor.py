"""The alignment-floor diagnostic (``evaluate_floor``): registrations replaced by the truth."""

from __future__ import annotations

import numpy as np
import pytest

from csr_core.alignment import evaluate_floor
from csr_core.sim import simulate_scenario

pytestmark = pytest.mark.unit


def test_true_registrations_reproduce_the_true_relative_poses_and_do_not_align_worse(tmp_path) -> None:
    scenario = tmp_path / "s"
    simulate_scenario("roundabout", 3, "standard", 5, scenario, trip_length_m=400.0)
    frame, recons = evaluate_floor.single_trip_results(scenario, None)
    truth = evaluate_floor.true_poses(scenario, frame, [r.trip.key for r in recons])
    seen: dict = {}
    evaluate_floor._aligned(recons, lambda m, sub: evaluate_floor._with_true_registration(m, sub, truth), seen)
    assert seen["matches"], "the trips share roads: there are accepted pairs"
    for m in seen["matches"]:
        si, sj = seen["submaps"][m.i], seen["submaps"][m.j]
        np.testing.assert_allclose(m.relative_pose(si.world_T_submap, sj.world_T_submap),
                                   evaluate_floor._true_relative(m, seen["submaps"], truth), atol=1e-9)
    r = evaluate_floor.evaluate(scenario)
    ate = r["ate_rmse_m"]
    assert ate["aligned"] < ate["smoothed"]
    assert ate["true_registrations"] <= ate["aligned"] + 0.02
    assert 0 <= r["pairs_off_m"]["mostly_along"] <= r["pairs_off_m"]["off"] <= r["accepted_pairs"]
