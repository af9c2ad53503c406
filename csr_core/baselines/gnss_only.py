"""GNSS-only baseline: raw GNSS poses (:mod:`gnss_poses`), every perceived element placed with
them and fused naively (:mod:`naive_fusion`). The floor any alignment must beat."""

from __future__ import annotations

import logging
from collections.abc import Sequence

import numpy as np

from csr_core.baselines.gnss_poses import gnss_poses_xyyaw
from csr_core.baselines.naive_fusion import KEYFRAME_SPACING_M, fuse_naively
from csr_core.errors import ReconstructionError
from csr_core.geo import LocalFrame
from csr_core.types import Reconstruction, Trip

log = logging.getLogger(__name__)


def gnss_only_poses(trips: Sequence[Trip], frame: LocalFrame) -> tuple[dict[str, np.ndarray], dict[str, str]]:
    """Raw GNSS poses per trip key, and the trips that have none (key -> reason)."""
    poses, failed = {}, {}
    for trip in trips:
        try:
            poses[trip.key] = gnss_poses_xyyaw(trip, frame)
        except ReconstructionError as exc:
            log.warning("%s", exc)
            failed[trip.key] = str(exc)
    return poses, failed


def reconstruct_gnss_only(
    trips: Sequence[Trip], frame: LocalFrame, spacing_m: float = KEYFRAME_SPACING_M
) -> Reconstruction:
    poses, failed = gnss_only_poses(trips, frame)
    return Reconstruction(
        origin_lat=frame.origin_lat,
        origin_lon=frame.origin_lon,
        poses_xyyaw_world=poses,
        map_features=fuse_naively(trips, poses, spacing_m),
        failed=failed,
        diagnostics={"method": "gnss_only"},
    )
