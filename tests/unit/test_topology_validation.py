"""Automatic validation of the fused map (paper III-E), called on hand-made features: which
evidence makes an instance suspect, and that thresholds follow the noise estimates."""

from __future__ import annotations

import numpy as np
import pytest

from csr_core.topology import DEFAULT
from csr_core.topology.validation import SUSPECT, validate
from csr_core.types import ElementType, MapFeature

pytestmark = pytest.mark.unit


def _line(
    fid: str,
    y: np.ndarray | float,
    *,
    support: int = 4,
    unc: float = 0.1,
    x0: float = 0.0,
    length: float = 40.0,
    etype: ElementType = ElementType.CENTERLINE,
    **props,
) -> MapFeature:
    x = np.arange(x0, x0 + length + 1e-9, 1.0)
    y = np.broadcast_to(np.asarray(y, float), x.shape) if np.ndim(y) == 0 else np.asarray(y, float)
    return MapFeature(
        etype,
        np.column_stack([x, y]),
        feature_id=fid,
        properties={
            "support_trips": support,
            "uncertainty_m": unc,
            "trips": [f"t{k}" for k in range(support)],
            **props,
        },
    )


def _kinds(features: list[MapFeature], cover: list[int] | None = None) -> dict[str | None, set[str]]:
    flags, _ = validate(
        features, cover if cover is not None else [f.properties["support_trips"] for f in features], DEFAULT
    )
    out: dict[str | None, set[str]] = {f.feature_id: set() for f in features}
    for fl in flags:
        out[fl.feature_id].add(fl.kind)
    return out


def test_a_copy_off_by_more_than_the_noise_is_flagged_on_the_less_supported_side() -> None:
    kinds = _kinds([_line("main", 0.0, support=5), _line("copy", 1.0, support=2, x0=10.0, length=20.0)])
    assert kinds["copy"] == {"implausible_lane_width"}
    assert kinds["main"] == set()


def test_the_duplicate_bound_follows_the_uncertainty_of_the_two_lines() -> None:
    # 0.5 m apart: beyond 2 combined sigmas of two 0.1 m lines (0.28 m), within those of 0.3 m lines (0.85 m)
    sharp = _kinds([_line("a", 0.0, support=5, unc=0.1), _line("b", 0.5, support=2, unc=0.1)])
    loose = _kinds([_line("a", 0.0, support=5, unc=0.3), _line("b", 0.5, support=2, unc=0.3)])
    assert "implausible_lane_width" in sharp["b"]
    assert "implausible_lane_width" not in loose["b"]


def test_adjacent_lanes_and_diverging_branches_are_not_copies() -> None:
    x = np.arange(0.0, 40.0 + 1e-9, 1.0)
    branch = np.clip((x - 10.0) * 0.1, 0.0, None)  # leaves the through lane at 10 m, 2 m off at 30 m
    kinds = _kinds(
        [_line("through", 0.0, support=5), _line("left", 3.5, support=1), _line("branch", branch, support=1)]
    )
    assert all("implausible_lane_width" not in k for k in kinds.values())


def test_low_support_is_a_single_trip_or_a_minority_of_the_trips_that_passed() -> None:
    lines = [
        _line("one", 0.0, support=1),
        _line("two", 20.0, support=2),
        _line("two_of_eight", 40.0, support=2),
    ]
    kinds = _kinds(lines, cover=[1, 2, 8])
    assert "low_support" in kinds["one"]
    assert "low_support" not in kinds["two"]  # two trips within the gate of each other confirm each other
    assert "low_support" in kinds["two_of_eight"]  # six trips passed and did not see it


def test_a_marking_one_trip_saw_is_reported_but_not_suspect() -> None:
    stop = _line("stop", 0.0, support=1, length=3.5, etype=ElementType.STOP_LINE)
    crosswalk = _line("crosswalk", 10.0, support=1, length=4.0, etype=ElementType.CROSSWALK)
    seen_twice = _line("stop2", 20.0, support=2, length=3.5, etype=ElementType.STOP_LINE)
    divider = _line("divider", 30.0, support=1, etype=ElementType.LANE_DIVIDER)
    flags, quality = validate([stop, crosswalk, seen_twice, divider], [1, 1, 2, 1], DEFAULT)
    kinds: dict[str, set[str]] = {}
    for fl in flags:
        kinds.setdefault(str(fl.feature_id), set()).add(fl.kind)
    assert kinds["stop"] == {"low_support_marking"} and kinds["crosswalk"] == {"low_support_marking"}
    assert "stop2" not in kinds  # two trips confirm each other
    assert kinds["divider"] == {"low_support"}  # a line one trip saw stays suspect
    assert "low_support_marking" not in SUSPECT


def test_a_gap_is_reported_but_does_not_make_the_instance_suspect() -> None:
    f = _line("gappy", 0.0, support=4, max_internal_gap_m=8.0)
    flags, quality = validate([f], [4], DEFAULT)
    assert [fl.kind for fl in flags] == ["gap"]
    assert "gap" not in SUSPECT and {"low_support", "implausible_lane_width"} <= SUSPECT
    assert all(q.score == 1.0 for q in quality.values())


def test_two_confirmed_lines_at_a_narrow_spacing_are_not_blamed() -> None:
    # similar support on both sides: the road's own narrow spacing (a taper), unless one is unconfirmed
    confirmed = _kinds([_line("a", 0.0, support=4), _line("b", 1.0, support=3)])
    single = _kinds([_line("a", 0.0, support=1), _line("b", 1.0, support=1)])
    assert confirmed == {"a": set(), "b": set()}
    assert "implausible_lane_width" in single["a"] and "implausible_lane_width" in single["b"]


def test_a_high_residual_pair_is_judged_against_the_noise_of_its_two_trips() -> None:
    from types import SimpleNamespace

    line = _line("l", 0.0, support=2)
    pair = SimpleNamespace(centre_xy_world=(20.0, 0.0), residual_rms_m=0.5, trip_key_i="t0", trip_key_j="t1")

    def flagged(trip_sigma_m: dict[str, float]) -> bool:
        flags, _ = validate([line], [2], DEFAULT, [pair], trip_sigma_m)
        return any(fl.kind == "high_residual_pair" for fl in flags)

    # expected residual: the two sigmas combined (0.14 m, 0.42 m); flagged above twice that
    assert flagged({"t0": 0.1, "t1": 0.1})
    assert not flagged({"t0": 0.3, "t1": 0.3})
    assert flagged({"t0": 0.1})  # a side without noise estimates (the pre-built map) counts as the other


def test_judged_rows_flatten_the_verdicts_flags_and_scalar_properties() -> None:
    from csr_core.topology.evaluate import judged_rows

    line = np.column_stack([np.arange(0.0, 30.5, 0.5), np.zeros(61)])
    f = MapFeature(
        ElementType.ROAD_BOUNDARY,
        line,
        feature_id="rb-1",
        properties={
            "flags": ["low_support", "gap"],
            "support_trips": 1,
            "passed_trips": 2,
            "uncertainty_m": 0.2,
            "trips": ["a"],
            "first_seen": "2026-11-01T00:00:00Z",
        },
    )
    (row,) = judged_rows([(f, True, False)])
    assert row["feature_id"] == "rb-1" and row["type"] == "road_boundary"
    assert row["length_m"] == pytest.approx(30.0)
    assert row["wrong"] and not row["wrong_beyond_local_offset"]
    assert row["suspect"] and row["flags"] == ["gap", "low_support"]
    assert row["passed_trips"] == 2 and row["uncertainty_m"] == 0.2 and "trips" not in row  # scalars only
