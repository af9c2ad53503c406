"""csr_core.pipeline: one entry point for the pipeline and the baselines."""

import dataclasses

import numpy as np
import pytest

from csr_core.bench.toy import ToySpec, make_toy_trips
from csr_core.errors import ReconstructionError
from csr_core.pipeline import Method, PipelineParams, reconstruct, world_frame
from csr_core.types import GnssStatus

pytestmark = pytest.mark.unit

SPEC = ToySpec(n_trips=2, length_m=150.0)


@pytest.mark.parametrize("method", list(Method))
def test_every_method_returns_poses_for_every_frame(method):
    trips, *_ = make_toy_trips(SPEC)
    recon = reconstruct(trips, PipelineParams(method=method))
    assert set(recon.poses_xyyaw_world) == {t.key for t in trips}
    for t in trips:
        assert recon.poses_xyyaw_world[t.key].shape == (t.n_frames, 3)
    assert recon.map_features
    assert recon.diagnostics["method"] == method.value


def test_the_pipeline_reports_which_stages_ran():
    trips, *_ = make_toy_trips(SPEC)
    recon = reconstruct(trips, PipelineParams(coarse=False))
    assert recon.diagnostics["stages"] == ["single_trip", "fine", "topology", "validation"]
    assert recon.diagnostics["coarse"] is False and recon.diagnostics["fine"] is True
    both = reconstruct(trips, PipelineParams())
    assert both.diagnostics["stages"] == ["single_trip", "coarse", "fine", "topology", "validation"]
    neither = reconstruct(trips, PipelineParams(coarse=False, fine=False))
    assert neither.diagnostics["stages"] == ["single_trip", "topology", "validation"]


def test_the_world_frame_comes_from_the_fixes_only():
    trips, *_ = make_toy_trips(dataclasses.replace(SPEC, n_trips=1))
    trip = trips[0]
    lonlat = trip.gnss_lonlat_deg.copy()
    lonlat[:10] = [0.0, 0.0]  # no-fix rows carry meaningless coordinates
    status = trip.gnss_status.copy()
    status[:10] = GnssStatus.NONE
    moved = dataclasses.replace(trip, gnss_lonlat_deg=lonlat, gnss_status=status)
    f = world_frame([moved])
    assert abs(f.origin_lat - 48.0) < 0.01 and abs(f.origin_lon - 11.0) < 0.01


def test_no_trips_or_no_fix_raise():
    with pytest.raises(ReconstructionError):
        reconstruct([])
    trips, *_ = make_toy_trips(dataclasses.replace(SPEC, n_trips=1))
    dead = dataclasses.replace(trips[0], gnss_status=np.full(trips[0].n_frames, GnssStatus.NONE, np.uint8))
    with pytest.raises(ReconstructionError):
        reconstruct([dead])


def test_params_are_frozen():
    with pytest.raises(dataclasses.FrozenInstanceError):
        PipelineParams().coarse = False  # type: ignore[misc]


def test_outputs_round_trip_through_the_scenario_readers(tmp_path):
    from csr_core.scenario import (
        geo_features_to_local,
        read_map_geojson,
        read_poses_dir,
        write_reconstruction,
    )
    from csr_core.se2 import wrap_angle

    trips, *_ = make_toy_trips(SPEC)
    recon = reconstruct(trips, PipelineParams(method=Method.GNSS_ONLY))
    failed_key = trips[1].key
    partial = dataclasses.replace(
        recon,
        poses_xyyaw_world={trips[0].key: recon.poses_xyyaw_world[trips[0].key]},
        failed={failed_key: "test failure"},
    )
    write_reconstruction(recon, trips, tmp_path)  # an earlier run with both trips
    write_reconstruction(partial, trips, tmp_path, {"extra": 1})
    tracks = read_poses_dir(tmp_path / "poses")
    assert list(tracks) == [trips[0].key]  # the failed trip has no CSV (not even a stale one)
    frame = world_frame(trips)
    xy = frame.to_local(tracks[trips[0].key].lonlat_deg)
    np.testing.assert_allclose(xy, recon.poses_xyyaw_world[trips[0].key][:, :2], atol=1e-3)
    # headings are written from true north: back into the plane through its meridian convergence
    track = tracks[trips[0].key]
    yaw = frame.yaw_rad(track.heading_deg, track.lonlat_deg)
    assert np.abs(wrap_angle(yaw - recon.poses_xyyaw_world[trips[0].key][:, 2])).max() < 1e-5
    feats = geo_features_to_local(read_map_geojson(tmp_path / "map.geojson"), frame)
    assert len(feats) == len(recon.map_features)
    for a, b in zip(feats, recon.map_features, strict=True):
        assert a.type == b.type
        np.testing.assert_allclose(a.points_xy_world, b.points_xy_world, atol=1e-3)
    import json

    report = json.loads((tmp_path / "report.json").read_text())
    assert report["failed"] == {failed_key: "test failure"} and report["trips_with_poses"] == 1


def test_features_of_degraded_trips_are_flagged_and_those_only_they_support_held_back():
    from csr_core.topology.degraded import DEGRADED_SUPPORT, hold_back_degraded
    from csr_core.types import ElementType, MapFeature

    def feature(fid: str, trips: list[str]) -> MapFeature:
        return MapFeature(
            ElementType.LANE_DIVIDER,
            np.array([[0.0, 0.0], [10.0, 0.0]]),
            feature_id=fid,
            properties={"trips": trips, "flags": []},
        )

    ghost = feature("ghost", ["c"])
    features = [feature("both", ["a", "b"]), feature("clean", ["a"]), feature("only", ["b"])]
    kept, held = hold_back_degraded(features, [ghost], {"b"})
    assert [f.feature_id for f in kept] == ["both", "clean"]
    assert [f.feature_id for f in held] == ["ghost", "only"]
    assert kept[0].properties["flags"] == [DEGRADED_SUPPORT] and kept[0].properties["degraded_trips"] == 1
    assert kept[1].properties["flags"] == []
    assert held[1].properties["flags"] == [DEGRADED_SUPPORT]
    assert hold_back_degraded(features, [ghost], set()) == (tuple(features), (ghost,))
