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
    assert recon.diagnostics["stages"][0] == "gnss_poses"
    assert recon.diagnostics["coarse"] is False and recon.diagnostics["fine"] is True


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
