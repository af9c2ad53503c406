"""What a tile keeps of each piece it aligned (``workers.tile_jobs.piece_outcome``): poses, blend
weights and the elements that go into the tile's map."""

from __future__ import annotations

import numpy as np
import pytest

from csr_core.alignment import AlignmentResult
from csr_core.tiling import blend_weight
from tests.unit.test_alignment_synthetic import make_scenario
from workers.tile_jobs import piece_outcome

pytestmark = pytest.mark.unit

HALO_M = 150.0


@pytest.fixture(scope="module")
def piece():
    trips, _ = make_scenario(n_trips=1, seed=3)[:2]
    return trips[0]


def _result(piece, failed: dict[str, str], aligned: np.ndarray | None = None) -> AlignmentResult:
    poses = {} if aligned is None else {piece.trip.key: aligned}
    return AlignmentResult(poses, failed, (), {}, {"unaligned_poses": {}})


def test_an_aligned_piece_moves_its_elements_with_its_alignment(piece):
    shifted = piece.poses_xyyaw_world + np.array([0.7, -0.2, 0.0])
    signed = np.linspace(-100.0, 200.0, piece.trip.n_frames)
    poses, weights, _, moved, failed = piece_outcome(piece, _result(piece, {}, shifted), signed, HALO_M)
    assert failed is None and np.allclose(poses, shifted)
    assert np.allclose(weights, blend_weight(signed, HALO_M))
    assert len(moved) == len(piece.instances)
    assert np.allclose(moved[0].points_xy_world, piece.instances[0].points_xy_world + [0.7, -0.2])


@pytest.mark.parametrize(
    "reason",
    [
        "no_consistent_match: none of 2 overlapping sub-maps passed",
        "no_overlap: no other trip or map area shares this trip's road",
    ],
)
def test_a_piece_not_aligned_here_keeps_its_elements_in_the_map_at_its_own_poses(piece, reason):
    """A road only this trip drove in the tile, past junctions its crossing trips do not match,
    stays in the map (dropping it lost a whole road: docs/pipeline.md); it has no say on the trip's
    poses (they follow the trip's aligned tiles), and only an unmatched one is a failure here."""
    signed = np.full(piece.trip.n_frames, 50.0)
    poses, weights, _, moved, failed = piece_outcome(
        piece, _result(piece, {piece.trip.key: reason}), signed, HALO_M
    )
    assert np.allclose(poses, piece.poses_xyyaw_world)
    assert len(moved) == len(piece.instances) > 0
    assert all(
        np.allclose(m.points_xy_world, i.points_xy_world) for m, i in zip(moved, piece.instances, strict=True)
    )
    assert not weights.any()
    assert failed == (None if reason.startswith("no_overlap") else reason)
