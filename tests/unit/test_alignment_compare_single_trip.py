"""``compare_single_trip``: a single-trip setting scored through the alignment beside the default."""

from __future__ import annotations

from dataclasses import replace

import pytest

from csr_core.alignment import align_trips, compare_single_trip
from csr_core.alignment.evaluate_failures import single_trip_results
from csr_core.alignment.evaluate_floor import ate_rmse_m, true_poses
from csr_core.sim import simulate_scenario
from csr_core.single_trip.params import DEFAULT as SINGLE_TRIP_DEFAULT

pytestmark = pytest.mark.unit


def test_a_changed_setting_is_run_cached_and_scored_apart_from_the_default(tmp_path) -> None:
    scenario = tmp_path / "s"
    simulate_scenario("roundabout", 3, "standard", 5, scenario, trip_length_m=400.0)
    cache = tmp_path / "cache"
    changed = replace(SINGLE_TRIP_DEFAULT, GNSS_BIAS_STATE=not SINGLE_TRIP_DEFAULT.GNSS_BIAS_STATE)
    rows = compare_single_trip.compare([scenario], changed, cache)
    ((name, a, b),) = rows
    assert name == "s"
    assert len(list(cache.glob("*.pkl"))) == 2  # one file per variant, neither overwriting the other
    # the default variant is the default stage and alignment, scored as the contract says
    frame, recons = single_trip_results(scenario, None)
    truth = true_poses(scenario, frame, [r.trip.key for r in recons])
    assert a.aligned_ate_m == pytest.approx(
        ate_rmse_m(align_trips(recons).poses_xyyaw_world, truth), abs=1e-9
    )
    # the changed stage smoothed the trips otherwise
    assert abs(b.trip_aligned_ate_m - a.trip_aligned_ate_m) > 1e-4
    # from the cache: the same figures, one progress line per scenario
    lines: list[str] = []
    assert compare_single_trip.compare([scenario], changed, cache, progress=lines.append) == rows
    assert len(lines) == 1 and lines[0].startswith("1/1 s: aligned")
    text = compare_single_trip.table(rows)
    assert "| s |" in text and "mean of 1" in text


def test_the_command_names_a_bad_setting_and_a_folder_that_is_no_scenario(tmp_path, capsys) -> None:
    with pytest.raises(SystemExit):
        compare_single_trip.main([str(tmp_path), "--single-trip-param", "NO_SUCH_FIELD=1"])
    assert "NO_SUCH_FIELD" in capsys.readouterr().err
    with pytest.raises(SystemExit):
        compare_single_trip.main([str(tmp_path), "--single-trip-param", "GNSS_BIAS_STATE=true"])
    assert "not a scenario folder" in capsys.readouterr().err
