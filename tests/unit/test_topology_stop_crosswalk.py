"""Known answers of the fusion of stop lines (robust straight axis) and crosswalks (robust
weighted per-vertex mean of the outlines), paper III-E."""

from __future__ import annotations

import numpy as np
import pytest
import shapely

from csr_core.topology import generate_topology
from csr_core.types import ElementNoise, ElementType, TripInstance

pytestmark = pytest.mark.unit

SL, CW = ElementType.STOP_LINE, ElementType.CROSSWALK
NOISE = {t: ElementNoise(0.05, 0.2, 100) for t in ElementType}  # trip sigma hypot(0.05, 0.10) = 0.11 m
STOP_LINE = np.array([[0.0, 0.0], [3.1, 0.0]])  # across one lane
RECT = np.array([[0.0, 0.0], [6.0, 0.0], [6.0, 3.0], [0.0, 3.0]])  # a crosswalk, 6 m x 3 m


def _trips(instances_per_trip: list[list[np.ndarray]], etype: ElementType) -> tuple[dict, dict]:
    trips = {
        f"veh-1__t{k:02d}": [TripInstance(etype, p, None, n_observations=8) for p in inst]
        for k, inst in enumerate(instances_per_trip)
    }
    return trips, {k: NOISE for k in trips}


def _stop_line(rng: np.random.Generator) -> np.ndarray:
    """One trip's stop line: a per-trip offset (5 cm) plus white noise (2 cm), a vertex every 0.5 m."""
    x = np.linspace(0.0, 3.1, 7)
    return np.column_stack([x, np.zeros_like(x)]) + rng.normal(0.0, 0.05, 2) + rng.normal(0.0, 0.02, (7, 2))


def test_a_stop_line_member_running_on_at_an_angle_neither_bends_nor_prolongs_it() -> None:
    """Nine trips agree; the tenth trip's splice crosses the stop line at 20 degrees and runs on
    2.7 m past its end (it went on into something else). Backbone growth followed it: the fused
    line came out bent and 5.8 m long. It is an outlier of the element, not a second one."""
    rng = np.random.default_rng(11)
    run_on = np.array([[-2.64, 1.05], [0.23, 0.46], [3.34, -0.70], [5.79, -2.11]])
    trips, noise = _trips([[_stop_line(rng)] for _ in range(9)] + [[run_on]], SL)
    res = generate_topology(trips, noise)
    assert len(res.features) == 1
    f = res.features[0]
    assert f.properties["support_trips"] == 9
    line = shapely.LineString(STOP_LINE)
    assert np.max(shapely.distance(shapely.points(f.points_xy_world), line)) < 0.08
    length = float(np.linalg.norm(np.diff(f.points_xy_world, axis=0), axis=1).sum())
    assert length == pytest.approx(3.1, abs=0.2)


def _crosswalk_scene(
    rng: np.random.Generator, n_trips: int, n_crosswalks: int, vertex_sigma_m: float
) -> tuple[dict, dict, np.ndarray]:
    """``n_crosswalks`` crosswalks 20 m apart, each outline seen by every trip with independent
    noise per vertex (vertex order rolled per trip)."""
    origins = np.column_stack([np.arange(n_crosswalks) * 20.0, np.zeros(n_crosswalks)])
    per_trip = []
    for k in range(n_trips):
        polys = [
            np.roll(RECT + o + rng.normal(0.0, vertex_sigma_m, RECT.shape), k % 4, axis=0) for o in origins
        ]
        per_trip.append(polys)
    trips, noise = _trips(per_trip, CW)
    return trips, noise, origins


def _vertex_errors(res, origins: np.ndarray) -> np.ndarray:
    """Per fused crosswalk vertex: distance to the nearest true corner."""
    errs = []
    for f in res.features:
        o = origins[int(np.argmin(np.linalg.norm(origins - f.points_xy_world.mean(0), axis=1)))]
        corners = RECT + o
        errs.append(np.min(np.linalg.norm(f.points_xy_world[:, None] - corners[None], axis=2), axis=1))
    return np.concatenate(errs)


def test_fused_crosswalk_shape_averages_the_vertex_noise_of_three_copies() -> None:
    """Three consistent copies with independent noise per vertex (sigma per coordinate). The
    per-vertex median has 0.449 sigma^2 per coordinate (RMS vertex error 0.95 sigma); the shape
    as the mean of the centred outlines (0.25 sigma^2) placed at the median of their centroids
    (0.112 sigma^2) has 0.36 sigma^2 (0.85 sigma). Over 300 crosswalks."""
    rng = np.random.default_rng(13)
    sigma = 0.05
    trips, noise, origins = _crosswalk_scene(rng, 3, 300, sigma)
    res = generate_topology(trips, noise)
    assert len(res.features) == 300
    rms = float(np.sqrt(np.mean(_vertex_errors(res, origins) ** 2)))
    assert rms < 0.90 * sigma


def test_noisy_crosswalk_copies_converge_to_it_and_a_misplaced_copy_is_ignored() -> None:
    """N copies with independent vertex noise (8 cm) and one extra copy 1 m off (a misplaced
    or clipped outline): the fused outline converges to the truth as 1 / sqrt(N) and the bad
    copy is the group's outlier."""
    sigma = 0.08
    for n_trips in (4, 16):
        rng = np.random.default_rng(14 + n_trips)
        trips, noise, origins = _crosswalk_scene(rng, n_trips, 20, sigma)
        bad = RECT + origins[0] + np.array([[1.0, 0.0], [1.0, 0.0], [0.0, 0.0], [0.0, 0.0]])
        trips["veh-1__bad"] = [TripInstance(CW, bad, None, n_observations=8)]
        noise["veh-1__bad"] = NOISE
        res = generate_topology(trips, noise)
        assert len(res.features) == 20
        rms = float(np.sqrt(np.mean(_vertex_errors(res, origins) ** 2)))
        assert rms < 1.2 * sigma * np.sqrt(2.0 / n_trips)
        first = min(res.features, key=lambda f: float(np.linalg.norm(f.points_xy_world.mean(0) - origins[0])))
        assert first.properties["outlier_trips"] == ["veh-1__bad"]
