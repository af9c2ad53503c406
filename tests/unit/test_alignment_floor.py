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
    evaluate_floor.align_with_matches(
        recons, lambda m, sub: evaluate_floor.with_true_registration(m, sub, truth), seen
    )
    assert seen["matches"], "the trips share roads: there are accepted pairs"
    for m in seen["matches"]:
        si, sj = seen["submaps"][m.i], seen["submaps"][m.j]
        np.testing.assert_allclose(
            m.relative_pose(si.world_T_submap, sj.world_T_submap),
            evaluate_floor._true_relative(m, seen["submaps"], truth),
            atol=1e-9,
        )
    figure = tmp_path / "stages.png"
    r = evaluate_floor.evaluate(scenario, figure=figure)
    assert figure.stat().st_size > 20_000  # two panels of frames drawn
    ate = r["ate_rmse_m"]
    assert ate["aligned"] < ate["smoothed"]
    assert ate["true_registrations"] <= ate["aligned"] + 0.02
    assert 0 <= r["pairs_off_m"]["mostly_along"] <= r["pairs_off_m"]["off"] <= r["accepted_pairs"]
    stages = r["error_by_stage"]
    assert set(stages) == set(evaluate_floor.STAGES)
    assert sum(s["frames_share"] for s in stages.values()) == pytest.approx(1.0)
    assert sum(s["squared_error_share"] for s in stages.values()) == pytest.approx(1.0)
    # three short trips overlap on about half their frames; what no pair holds is the error
    assert 0.25 < stages["registered"]["frames_share"] < 0.75
    assert stages["registered"]["rms_m"] < stages["no_candidate_pair"]["rms_m"]
    # the stages partition the frames: together they give the aligned ATE
    ms = sum(s["frames_share"] * s["rms_m"] ** 2 for s in stages.values() if s["frames_share"] > 0)
    assert np.sqrt(ms) == pytest.approx(ate["aligned"], rel=1e-6)


def test_param_assignments_change_the_named_fields_and_reject_unknown_ones() -> None:
    p = evaluate_floor.parse_params(["topo_split_merge_z=1.5", "fine=false", "max_partners_per_submap=3"])
    assert p.topo_split_merge_z == 1.5 and p.fine is False and p.max_partners_per_submap == 3
    assert evaluate_floor.parse_params([]) == evaluate_floor.DEFAULT
    with pytest.raises(ValueError, match="no_such_field"):
        evaluate_floor.parse_params(["no_such_field=1"])
    with pytest.raises(ValueError, match="NAME=VALUE"):
        evaluate_floor.parse_params(["topo_split_merge_z"])
