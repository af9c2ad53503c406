"""The single-trip benchmark's target bookkeeping (``csr_core.bench.single_trip``)."""

from __future__ import annotations

import pytest

from csr_core.bench.single_trip import render_section, world_summary

pytestmark = pytest.mark.unit


def _result(
    world: str,
    seed: int,
    correctness: float,
    *,
    true_poses: bool = False,
    profile: str = "standard",
    rpe: float = 0.02,
    jump_err: float = float("nan"),
) -> dict:
    scores = {"correctness": correctness, "completeness": 0.95, "per_type": {}}
    return {
        "spec": f"{world}-{profile}-10x-1500m-s{seed}",
        "world": world,
        "profile": profile,
        "seed": seed,
        "true_poses": true_poses,
        "trips": 10,
        "km": 15.0,
        "ate_raw_gnss_m": 0.8,
        "ate_smoothed_m": 0.6,
        "ate_trip_aligned_m": 0.2,
        "rpe_raw_gnss_m": 0.2,
        "rpe_smoothed_m": rpe,
        "jump_frames": 0 if jump_err != jump_err else 12,
        "jump_max_smoothed_err_m": jump_err,
        "rigid": scores,
        "local": scores | {"correctness": 0.99},
        "local_offset_m": 100.0,
        "seconds_per_km": 0.3,
        "noise": {"lane_divider": {"estimated_lateral_sigma_m": 0.10, "observed_lateral_sigma_m": 0.12}}
        if true_poses
        else {},
    }


def test_a_target_is_met_only_when_every_seed_meets_it():
    results = [
        _result("urban", 1, 0.99),
        _result("urban", 2, 0.96),
        _result("rural", 1, 0.99),
        _result("rural", 1, 0.90, true_poses=True),
        _result("urban", 1, 0.5, profile="hard"),
    ]
    by_world = {s["world"]: s for s in world_summary(results)}
    assert list(by_world) == ["urban", "rural"]  # the benchmark's world order; hard rows left out
    assert by_world["urban"]["rigid_correctness"] == pytest.approx(0.975)  # the mean passes ...
    assert not by_world["urban"]["rigid_ok"]  # ... but seed 2 does not
    assert by_world["urban"]["rigid_min_correctness"] == 0.96 and by_world["urban"]["local_ok"]
    assert by_world["rural"]["rigid_ok"] and by_world["rural"]["true_correctness"] == 0.90
    assert by_world["urban"]["rpe_ratio"] == pytest.approx(0.1) and by_world["urban"]["rpe_ok"]


def test_a_jump_beyond_the_bound_is_marked_and_no_jump_is_not():
    results = [
        _result("urban", 1, 0.99),
        _result("urban", 1, 0.99, profile="hard", jump_err=3.4),
        _result("rural", 1, 0.99, profile="hard"),
    ]
    text = render_section(results, None, None, 60.0, sets=("standard", "hard"))
    jumps = text.split("### Hard profile")[1].split("###")[0]
    assert "| urban-hard-10x-1500m-s1 | 10 | 12 | 3.40 | **no** |" in jumps
    assert "| rural-hard-10x-1500m-s1 | 10 | 0 |  | yes |" in jumps


def test_noise_estimates_are_tabled_from_the_true_pose_runs():
    results = [
        _result("rural", 1, 0.99),
        _result("rural", 1, 0.99, true_poses=True),
        _result("rural", 2, 0.99, true_poses=True),
    ]
    noise = render_section(results, None, None, 60.0).split("### Noise estimates")[1].split("###")[0]
    assert "| rural | 0.100 / 0.120 |  |  |" in noise


def test_evaluate_param_names_a_field_or_is_refused(capsys):
    from csr_core.single_trip import evaluate

    with pytest.raises(SystemExit) as exc:
        evaluate.main(["no-such-folder", "--param", "DASH_CHAINNG=false"])
    assert exc.value.code == 2
    assert "DASH_CHAINNG=false" in capsys.readouterr().err


def test_the_cpu_per_stage_is_tabled_per_world_with_the_machine_reference():
    stages = {"poses": 0.10, "tracking": 0.04, "splicing": 0.30, "unseen_cut": 0.03, "noise": 0.01}
    results = [
        _result("urban", seed, 0.99)
        | {"stage_seconds_per_km": {k: v * seed for k, v in stages.items()}, "machine_reference_s": 0.16}
        for seed in (1, 2)
    ]
    text = render_section(results, None, None, 60.0, sets=("standard",))
    table = text.split("### Where the CPU goes")[1].split("###")[0]
    assert "| world | poses | tracking | splicing | unseen_cut | noise | all |" in table
    assert "| urban | 0.150 | 0.060 | 0.450 | 0.045 | 0.015 | 0.300 |" in table  # means over the seeds
    assert "Machine reference: 0.160 CPU s" in table


def test_reconstruct_trip_reports_the_cpu_of_every_stage():
    from csr_core.single_trip import STAGES, reconstruct_trip
    from csr_core.single_trip.synthetic import SynthSpec, make_trip

    trip, _, frame = make_trip(SynthSpec(length_m=150.0, gnss_sigma_m=0.2, seed=3))
    cpu = reconstruct_trip(trip, frame).diagnostics["cpu_seconds"]
    assert list(cpu) == list(STAGES)
    assert all(v >= 0.0 for v in cpu.values()) and cpu["poses"] > 0.0
