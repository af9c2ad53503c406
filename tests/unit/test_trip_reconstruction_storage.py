"""The region frame of a trip (``csr_core.geo.region_frame_for``) and the stored form of a
single-trip reconstruction (``services.reconstructions``): known answers and round trips."""

from __future__ import annotations

import mercantile
import numpy as np
import pytest

from csr_core.geo import region_frame_for
from csr_core.single_trip import reconstruct_trip
from csr_core.upload import decode_trip
from services.cli.bench_ingest import straight_trip
from services.reconstructions import (
    ALGORITHM_VERSION,
    decode_arrays,
    instance_from_json,
    noise_from_json,
    row_values,
)

pytestmark = pytest.mark.unit


def test_region_frame_is_the_centre_of_the_zoom_10_tile_of_the_point():
    lonlat = (11.5790, 48.1366)  # Munich
    tile = mercantile.tile(*lonlat, 10)
    assert (tile.x, tile.y) == (544, 355)
    frame = region_frame_for(lonlat)
    centre = mercantile.ul(tile.x + 0.5, tile.y + 0.5, 10)
    assert (frame.origin_lon, frame.origin_lat) == pytest.approx((centre.lng, centre.lat))
    np.testing.assert_allclose(frame.to_local([[centre.lng, centre.lat]]), [[0.0, 0.0]], atol=1e-6)
    # any point of that tile gets the same frame; a point of the next tile another one
    west, south, east, north = mercantile.bounds(tile)
    assert (
        region_frame_for((west + 1e-6, north - 1e-6))
        == frame
        == region_frame_for((east - 1e-6, south + 1e-6))
    )
    assert region_frame_for((east + 1e-6, south + 1e-6)) != frame


def test_a_stored_reconstruction_decodes_to_what_was_computed():
    trip = decode_trip(straight_trip(vehicle_id="veh-1", trip_id="t-1", length_m=200.0))
    frame = region_frame_for(trip.gnss_lonlat_deg[0])
    recon = reconstruct_trip(trip, frame)
    values = row_values(recon, frame)
    assert values["algorithm_version"] == ALGORITHM_VERSION
    assert (values["origin_lat"], values["origin_lon"]) == (frame.origin_lat, frame.origin_lon)
    assert (values["n_frames"], values["n_instances"]) == (trip.n_frames, len(recon.instances))
    arrays = decode_arrays(values["arrays"])
    np.testing.assert_array_equal(arrays["poses_xyyaw_world"], recon.poses_xyyaw_world)
    np.testing.assert_allclose(arrays["pose_sigma_xy_m"], recon.pose_sigma_xy_m, rtol=1e-6)
    np.testing.assert_array_equal(arrays["keyframe_indices"], recon.keyframe_indices)
    assert recon.white_poses_xyyaw_world is not None  # the bias state's white solve, kept apart
    np.testing.assert_array_equal(arrays["white_poses_xyyaw_world"], recon.white_poses_xyyaw_world)
    for stored, computed in zip(values["instances"], recon.instances, strict=True):
        back = instance_from_json(stored)
        assert (back.type, back.style, back.n_observations) == (
            computed.type,
            computed.style,
            computed.n_observations,
        )
        np.testing.assert_allclose(back.points_xy_world, computed.points_xy_world, atol=5e-4)  # mm rounding
    noise = noise_from_json(values["noise"])
    assert set(noise) == set(recon.noise)
    for kind, computed_noise in recon.noise.items():
        assert noise[kind].lateral_sigma_m == pytest.approx(computed_noise.lateral_sigma_m)
        assert noise[kind].n_samples == computed_noise.n_samples


def test_the_white_solve_follows_a_reconstruction_through_crop_and_reframe():
    """The white-noise solve's poses are cut with the frames of a tile piece and re-projected
    with the smoothed ones; a reconstruction without them stores none."""
    from dataclasses import replace

    from csr_core.geo import LocalFrame
    from csr_core.tiling import crop_reconstruction, reframe_reconstruction

    trip = decode_trip(straight_trip(vehicle_id="veh-1", trip_id="t-1", length_m=200.0))
    frame = region_frame_for(trip.gnss_lonlat_deg[0])
    recon = reconstruct_trip(trip, frame)
    prior = recon.white_poses_xyyaw_world
    piece = crop_reconstruction(recon, 20, 120, suffix="a")
    np.testing.assert_array_equal(piece.white_poses_xyyaw_world, prior[20:120])
    other = LocalFrame(frame.origin_lat + 0.01, frame.origin_lon + 0.01)
    moved = reframe_reconstruction(recon, frame, other)
    np.testing.assert_allclose(
        moved.white_poses_xyyaw_world[:, :2], other.to_local(frame.to_lonlat(prior[:, :2])), atol=1e-6
    )
    without = replace(recon, white_poses_xyyaw_world=None)
    assert "white_poses_xyyaw_world" not in decode_arrays(row_values(without, frame)["arrays"])
