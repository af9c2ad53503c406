"""The absolute 1-sigma of a map element (Eq. 1 of ``csr_core.topology.absolute_uncertainty``),
the per-trip GNSS bias sigma it is made of, and the tile certificate."""

from __future__ import annotations

import math

import numpy as np
import pytest

from csr_core.single_trip.gnss_bias import bias_correlation_length_m
from csr_core.single_trip.params import SingleTripParams
from csr_core.topology.absolute_uncertainty import (
    SIGMA_ABS_PROPERTY,
    TRIP_BIAS_LENGTH_KEY,
    TRIP_BIAS_SIGMA_KEY,
    UNKNOWN_TRIP_BIAS_SIGMA_M,
    TripBias,
    absolute_sigma_m,
    passes_needed,
    tied_trips,
    tile_certificate,
    trip_bias_sigma_m,
    trip_biases,
    with_absolute_uncertainty,
)
from csr_core.types import ElementType, GnssStatus, MapFeature

pytestmark = pytest.mark.unit


def test_more_passes_give_a_smaller_sigma_and_never_below_the_relative_one():
    u = 0.04
    sigmas = [absolute_sigma_m(u, [0.6] * n) for n in (1, 2, 4, 16, 64, 10_000)]
    assert all(a > b for a, b in zip(sigmas, sigmas[1:], strict=False))
    assert all(s >= u for s in sigmas)
    assert sigmas[-1] == pytest.approx(u, rel=0.02)


def test_equal_trips_give_the_bias_over_sqrt_n():
    # Eq. 1 with n trips of one sigma s: sqrt(u^2 + s^2 / n)
    rng = np.random.default_rng(3)
    for _ in range(20):
        u, s, n = rng.uniform(0.01, 0.3), rng.uniform(0.05, 3.0), int(rng.integers(1, 50))
        assert absolute_sigma_m(u, [s] * n) == pytest.approx(math.sqrt(u * u + s * s / n))


def test_trips_combine_by_information():
    # an RTK trip dominates single-point ones: the combined variance is 1 / sum(1 / s_i^2)
    rtk, single = 0.05, 1.0
    assert absolute_sigma_m(0.0, [rtk, single, single]) == pytest.approx(
        1.0 / math.sqrt(1 / rtk**2 + 2 / single**2)
    )
    assert absolute_sigma_m(0.0, [rtk, single]) < rtk


def test_no_trip_counts_as_an_unknown_receiver_and_bad_sigmas_raise():
    assert absolute_sigma_m(0.02, []) == pytest.approx(math.hypot(0.02, UNKNOWN_TRIP_BIAS_SIGMA_M))
    with pytest.raises(ValueError, match="positive and finite"):
        absolute_sigma_m(0.02, [0.5, 0.0])
    with pytest.raises(ValueError, match="positive and finite"):
        absolute_sigma_m(0.02, [math.inf])


def test_trip_bias_sigma_is_the_median_reported_std_else_the_status_table():
    params = SingleTripParams()
    status = np.array([GnssStatus.SINGLE] * 5 + [GnssStatus.NONE] * 3, np.uint8)
    std = np.array([0.5, 0.6, 0.7, 0.8, 0.9, 0.1, 0.1, 0.1])
    assert trip_bias_sigma_m(status, std, params) == pytest.approx(0.7)  # fixes only
    no_std = np.full(8, np.nan)
    assert trip_bias_sigma_m(status, no_std, params) == pytest.approx(
        params.GNSS_SIGMA_BY_STATUS_M[int(GnssStatus.SINGLE)]
    )
    rtk = np.full(4, int(GnssStatus.RTK_FIXED), np.uint8)
    assert trip_bias_sigma_m(rtk, np.full(4, 0.001), params) == pytest.approx(params.GNSS_SIGMA_FLOOR_M)
    none = np.full(4, int(GnssStatus.NONE), np.uint8)
    assert trip_bias_sigma_m(none, np.full(4, np.nan), params) == UNKNOWN_TRIP_BIAS_SIGMA_M
    with pytest.raises(ValueError, match="differ in shape"):
        trip_bias_sigma_m(status, std[:3], params)


def test_features_get_sigma_abs_from_their_trips():
    line = np.array([[0.0, 0.0], [10.0, 0.0]])
    seen_twice = MapFeature(
        ElementType.LANE_DIVIDER, line, properties={"trips": ["a", "b"], "uncertainty_m": 0.03}
    )
    seen_by_stranger = MapFeature(
        ElementType.LANE_DIVIDER, line, properties={"trips": ["z"], "uncertainty_m": 0.03}
    )
    biases = {"a": TripBias(0.4, 1000.0), "b": TripBias(0.4, 1000.0)}
    out = with_absolute_uncertainty([seen_twice, seen_by_stranger], biases)
    assert out[0].properties[SIGMA_ABS_PROPERTY] == pytest.approx(math.sqrt(0.03**2 + 0.4**2 / 2), abs=1e-4)
    assert out[1].properties[SIGMA_ABS_PROPERTY] == pytest.approx(
        math.hypot(0.03, UNKNOWN_TRIP_BIAS_SIGMA_M), abs=1e-4
    )
    assert SIGMA_ABS_PROPERTY not in seen_twice.properties  # the input is left alone


def test_passes_needed_reaches_the_target_under_the_model():
    u, s, n, target = 0.03, 0.5, 4, 0.10
    now = absolute_sigma_m(u, [s] * n)
    k = passes_needed(now, u, n, target)
    assert k is not None
    assert absolute_sigma_m(u, [s] * (n + k)) <= target + 1e-12
    assert absolute_sigma_m(u, [s] * (n + k - 1)) > target
    assert passes_needed(0.05, 0.03, 4, target) == 0
    assert passes_needed(0.5, 0.2, 4, target) is None  # the relative part alone is above it


def test_tile_certificate_weighs_by_length():
    cert = tile_certificate([30.0, 10.0], [0.2, 0.4], [0.02, 0.04], [4, 2], trips=5, target_m=0.1)
    assert cert.expected_absolute_error_m == pytest.approx(math.sqrt((30 * 0.04 + 10 * 0.16) / 40))
    assert cert.expected_relative_error_m == pytest.approx(math.sqrt((30 * 0.0004 + 10 * 0.0016) / 40))
    assert cert.trips == 5 and cert.n_features == 2 and cert.passes_median == 3.0
    assert cert.passes_needed == passes_needed(
        cert.expected_absolute_error_m, cert.expected_relative_error_m, 3.0, 0.1
    )
    empty = tile_certificate([], [], [], [], trips=0, target_m=0.1)
    assert empty.n_features == 0 and empty.passes_needed is None
    with pytest.raises(ValueError, match="one entry per element"):
        tile_certificate([1.0], [0.1, 0.2], [0.0], [1], trips=1, target_m=0.1)
    with pytest.raises(ValueError, match="target_m"):
        tile_certificate([], [], [], [], trips=0, target_m=0.0)


def test_trips_passing_within_their_bias_length_are_tied_to_the_element():
    element = np.array([[0.0, 0.0], [20.0, 0.0]])
    road = np.stack([np.linspace(-500, 500, 201), np.full(201, 0.0)], axis=1)
    paths = {
        "own": road,
        "near": road + [0.0, 300.0],  # 300 m away, within its 600 m
        "far": road + [0.0, 900.0],  # beyond its 600 m
        "slow": road + [0.0, 300.0],  # 300 m away, beyond its 100 m
    }
    biases = {k: TripBias(0.5, 600.0) for k in ("own", "near", "far")} | {"slow": TripBias(0.5, 100.0)}
    assert tied_trips(element, ["own"], paths, biases) == ["near", "own"]
    feature = MapFeature(
        ElementType.LANE_DIVIDER, element, properties={"trips": ["own"], "uncertainty_m": 0.05}
    )
    (alone,) = with_absolute_uncertainty([feature], biases)
    (tied,) = with_absolute_uncertainty([feature], biases, paths)
    assert alone.properties[SIGMA_ABS_PROPERTY] == pytest.approx(math.hypot(0.05, 0.5), abs=1e-4)
    assert tied.properties[SIGMA_ABS_PROPERTY] == pytest.approx(math.sqrt(0.05**2 + 0.25 / 2), abs=1e-4)


def test_bias_length_is_the_distance_of_one_correlation_time():
    params = SingleTripParams()
    t = np.arange(0.0, 60.0, 0.1)
    xy = np.stack([12.0 * t, np.zeros_like(t)], axis=1)  # 12 m/s
    assert bias_correlation_length_m(t, xy, params) == pytest.approx(12.0 * params.GNSS_BIAS_TAU_S)
    assert bias_correlation_length_m(t[:1], xy[:1], params) == 0.0
    with pytest.raises(ValueError, match="positions_xy"):
        bias_correlation_length_m(t, xy[:10], params)
    diagnostics = {"a": {TRIP_BIAS_SIGMA_KEY: 0.6, TRIP_BIAS_LENGTH_KEY: 900.0}, "old": {"odom_scale": 1.0}}
    assert trip_biases(diagnostics) == {"a": TripBias(0.6, 900.0)}
