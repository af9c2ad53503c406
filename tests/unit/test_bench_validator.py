"""The validator benchmark's pooling and section (``csr_core.bench.validator``)."""

from __future__ import annotations

import pytest

from csr_core.bench.validator import pooled, render_section

pytestmark = pytest.mark.unit


def _fleet(
    spec: str, instances: int, wrong: int, flagged: int, caught: int, per_flag: dict | None = None
) -> dict:
    v = {
        "instances": instances,
        "wrong": wrong,
        "flagged": flagged,
        "recall": caught / max(wrong, 1),
        "precision": caught / max(flagged, 1),
        "per_flag": per_flag or {},
        "beyond_local_offset": {
            "wrong": wrong,
            "flagged": flagged,
            "recall": caught / max(wrong, 1),
            "precision": caught / max(flagged, 1),
        },
    }
    return {
        "spec": spec,
        "world": spec.split("-")[0],
        "seed": 1,
        "trips": 8,
        "mcd": 0.1,
        "validator": v,
        "figure": None,
    }


def test_instances_are_pooled_not_fleets_averaged():
    fleets = [
        _fleet("urban-hard-8x-1500m-s5", 400, 40, 100, 36),
        _fleet("rural-hard-8x-1500m-s11", 20, 16, 4, 4),
    ]
    total = pooled(fleets)
    assert (total["wrong"], total["flagged"], total["caught"]) == (56, 104, 40)
    assert total["recall"] == pytest.approx(40 / 56) and total["precision"] == pytest.approx(40 / 104)
    # the mean of the fleets' recalls would be (0.9 + 0.25) / 2 = 0.575: a small fleet must not weigh as much


def test_the_bound_is_reported_met_only_when_both_hold_and_nothing_wrong_is_not_a_score():
    flags = {"low_support": {"flagged": 90, "wrong": 46, "alone": 70, "alone_wrong": 30}}
    met = render_section([_fleet("urban-hard-8x-1500m-s5", 400, 50, 90, 46, flags)], None, None, 60.0)
    assert "recall 0.920 (46 of 50" in met and "precision 0.511" in met and ": met.**" in met
    assert "| low_support | 90 | 46 | 0.51 | 70 | 30 |" in met
    low_precision = render_section([_fleet("urban-hard-8x-1500m-s5", 400, 50, 120, 46)], None, None, 60.0)
    assert ": not met.**" in low_precision
    clean = render_section([_fleet("toy-toy-3x-300m-s1", 11, 0, 0, 0)], None, None, 60.0)
    assert "recall n/a (0 of 0" in clean and ": not met.**" in clean and "(no instance flagged)" in clean


def test_the_section_says_what_a_validator_can_reach_from_the_judged_instances(tmp_path):
    def inst(wrong: bool, suspect: bool, support: int) -> dict:
        return {
            "type": "lane_divider",
            "length_m": 20.0,
            "wrong": wrong,
            "suspect": suspect,
            "flags": [],
            "support_trips": support,
            "scatter_ratio": 0.5,
            "rejected_weight_share": 0.0,
        }

    fleets = []
    for k, spec in enumerate(("urban-hard-8x-1500m-s5", "rural-hard-8x-1500m-s11")):
        f = _fleet(spec, 40, 4, 8, 3)
        f["instances"] = (
            [inst(True, True, 1)] * 3
            + [inst(False, True, 1)] * 5
            + [inst(True, False, 3)]
            + [inst(False, False, 3)] * (31 - k)
        )
        fleets.append(f)
    text = render_section(fleets, None, None, 60.0)
    assert "### What a validator can reach here" in text
    assert "| one trip | 16 | 6 | 0.375 | 16 | 6 |" in text
    assert "| trips agree | 63 | 2 | 0.032 | 0 | 0 |" in text
    assert "2 of the 8 wrong instances are instances that two or more trips agree on" in text
    assert "would reach recall 0.750" in text
    assert "logistic regression: precision" in text and "boosted trees: precision" in text
    drawn = render_section(fleets, None, tmp_path, 60.0, reach_figure=tmp_path / "figures" / "reach.png")
    assert (tmp_path / "figures" / "reach.png").stat().st_size > 10_000
    assert "(figures/reach.png)" in drawn
    assert "### What a validator can reach" not in render_section(
        [_fleet("urban-hard-8x-1500m-s5", 40, 4, 8, 3)], None, None, 60.0
    )
