"""Courses are clockwise from true north; a local tmerc plane's grid north turns away from it off
the plane's central meridian (the meridian convergence). A trip's course must come into the plane
and its poses' headings go out through it, or a trip kilometres off its frame's meridian (the
service's region frames) carries a heading bias that its course factors pin."""

import dataclasses

import numpy as np
import pytest

from csr_core import metrics, se2
from csr_core.geo import LocalFrame
from csr_core.single_trip import reconstruct_trip
from csr_core.single_trip.params import DEFAULT
from csr_core.tiling import reframe_poses
from csr_core.types import Trip
from tests.unit.test_single_trip_gnss_course import _weaving_trip

pytestmark = pytest.mark.unit


def test_a_grid_heading_points_where_true_north_points_in_the_plane():
    frame = LocalFrame(origin_lat=49.0, origin_lon=8.4)
    lonlat = np.array([[8.6, 49.05], [8.2, 48.95], [8.4, 49.2]])
    a, b = frame.to_local(lonlat), frame.to_local(lonlat + [0.0, 1e-4])
    north_yaw = np.arctan2(b[:, 1] - a[:, 1], b[:, 0] - a[:, 0])
    yaw = se2.heading_deg_to_yaw_rad(frame.grid_heading_deg(np.zeros(3), lonlat))
    assert np.abs(se2.wrap_angle(yaw - north_yaw)).max() < 1e-7
    # about (lon - lon_0) sin(lat): 0.15 degrees 15 km east of the central meridian, none on it
    assert np.degrees(frame.convergence_rad(lonlat)) == pytest.approx([0.151, -0.151, 0.0], abs=0.002)
    headings = np.array([0.0, 359.99, 123.4])
    assert frame.true_heading_deg(frame.grid_heading_deg(headings, lonlat), lonlat) == pytest.approx(headings)
    assert np.isnan(frame.grid_heading_deg(np.array([np.nan]), lonlat[:1])).all()


def _trip_far_east(seed: int) -> tuple[Trip, np.ndarray, LocalFrame]:
    """The course test's weaving DGPS trip, placed 15 km east of ``near``'s central meridian, its
    courses as a receiver reports them (from true north)."""
    t, true, odom, gnss_xy, status, std, grid_heading = _weaving_trip(seed)
    near = LocalFrame(origin_lat=49.0, origin_lon=8.6)
    lonlat = near.to_lonlat(gnss_xy)
    trip = Trip(
        "v",
        f"s{seed}",
        "2026-11-28T00:00:00Z",
        t,
        lonlat,
        status,
        std,
        near.true_heading_deg(grid_heading, lonlat),
        odom,
        tuple(() for _ in t),
    )
    return trip, true, near


def test_a_trip_off_its_frame_s_meridian_is_smoothed_as_on_it():
    """The same trip smoothed in a frame centred on it and in one 15 km west (0.15 degrees of
    convergence, the region frames' size): with every fix's course held, the two agree to a
    centimetre once moved into one frame, and both are as close to the truth."""
    params = dataclasses.replace(DEFAULT, GNSS_HEADING_PER_FIX=True)
    far = LocalFrame(origin_lat=49.0, origin_lon=8.4)
    for seed in range(2):
        trip, true, near = _trip_far_east(seed)
        on_meridian = reconstruct_trip(trip, near, params).poses_xyyaw_world
        off_meridian = reframe_poses(reconstruct_trip(trip, far, params).poses_xyyaw_world, far, near)
        gap_m = np.linalg.norm(off_meridian[:, :2] - on_meridian[:, :2], axis=1)
        assert gap_m.max() < 0.01, gap_m.max()
        assert np.abs(se2.wrap_angle(off_meridian[:, 2] - on_meridian[:, 2])).max() < np.radians(0.005)
        assert metrics.position_errors(on_meridian[:, :2], true[:, :2]).max() < 1.5
