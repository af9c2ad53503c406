"""The whole reconstruction in one process (``csr reconstruct``, contract section 4).

:func:`reconstruct` is the project's pipeline written as a recipe, one comment per stage of the
paper (section III): smooth, split, associate, optimize, refine, fuse, validate. Stages that do
not exist yet are not there yet; until they are, the recipe falls back to the GNSS-only
baseline for poses and the baselines' naive fusion for the map, and says so in
``diagnostics["stages"]``.

The same entry point runs the benchmark's baselines (``Method.GNSS_ONLY``, ``Method.ROADMAP_ICP``)
and the ablation of Table I (``coarse`` / ``fine`` flags) so every column of the benchmark goes
through one code path. The world frame is ``LocalFrame.around(all GNSS fixes)``: the pipeline
sees only the trips, never the scenario's truth or its origin.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Sequence
from dataclasses import dataclass
from enum import StrEnum

import numpy as np

from csr_core.baselines.gnss_only import gnss_only_poses, reconstruct_gnss_only
from csr_core.baselines.naive_fusion import KEYFRAME_SPACING_M, fuse_naively
from csr_core.baselines.roadmap_icp import CHUNK_LENGTH_M, reconstruct_roadmap_icp
from csr_core.errors import ReconstructionError
from csr_core.geo import LocalFrame
from csr_core.types import Reconstruction, Trip

log = logging.getLogger(__name__)


class Method(StrEnum):
    PIPELINE = "pipeline"
    GNSS_ONLY = "gnss_only"
    ROADMAP_ICP = "roadmap_icp"


@dataclass(frozen=True, slots=True)
class PipelineParams:
    """What ``csr reconstruct`` runs. ``coarse`` / ``fine`` switch the two alignment stages
    (paper III-D; Table I ablation) once they exist."""

    method: Method = Method.PIPELINE
    coarse: bool = True
    fine: bool = True
    keyframe_spacing_m: float = KEYFRAME_SPACING_M
    icp_chunk_length_m: float = CHUNK_LENGTH_M


def world_frame(trips: Sequence[Trip]) -> LocalFrame:
    """The batch's world plane, centred on all GNSS fixes (rows with a fix only)."""
    fixes = [t.gnss_lonlat_deg[t.has_fix] for t in trips]
    fixes = [f for f in fixes if len(f)]
    if not fixes:
        raise ReconstructionError("no trip has a GNSS fix: the world frame is undefined")
    return LocalFrame.around(np.concatenate(fixes))


def reconstruct(trips: Sequence[Trip], params: PipelineParams = PipelineParams()) -> Reconstruction:
    """Trips (in upload order) -> :class:`Reconstruction` (poses of every frame, map, failures)."""
    if not trips:
        raise ReconstructionError("no trips to reconstruct")
    frame = world_frame(trips)
    if params.method == Method.GNSS_ONLY:
        return reconstruct_gnss_only(trips, frame, params.keyframe_spacing_m)
    if params.method == Method.ROADMAP_ICP:
        return reconstruct_roadmap_icp(trips, frame, params.icp_chunk_length_m, params.keyframe_spacing_m)
    return _csr_pipeline(trips, frame, params)


def _csr_pipeline(trips: Sequence[Trip], frame: LocalFrame, params: PipelineParams) -> Reconstruction:
    stages: list[str] = []
    timings_s: dict[str, float] = {}
    t0 = time.perf_counter()

    # 1. smooth: single-trip pose graph + element tracking (paper III-C, Eq. 2).
    #    Not wired yet: raw GNSS poses (outages bridged by odometry) stand in.
    #    Plug-in: for each trip, recon = csr_core.single_trip.reconstruct_trip(trip, frame) (a
    #    ReconstructionError -> failed[trip.key] = str(exc)); poses_by_key from recon.poses_xyyaw_world;
    #    stages.append("single_trip").
    poses_by_key, failed = gnss_only_poses(trips, frame)
    stages.append("gnss_poses")
    timings_s["smooth"] = time.perf_counter() - t0

    # 2. split: sub-maps per trip (III-D-1, Fig. 4).            -- not there yet
    # 3. associate: sub-map matching pairs across trips.        -- not there yet
    # 4. optimize: coarse incremental pose graph (Eq. 9-12), if params.coarse.  -- not there yet
    # 5. refine: fine, frame-level alignment, if params.fine.  -- not there yet
    #    Plug-in (2-5 in one call): result = csr_core.alignment.align_trips(trip_recons,
    #    params=dataclasses.replace(AlignmentParams(), coarse=params.coarse, fine=params.fine));
    #    poses_by_key = result.poses_xyyaw_world; failed |= result.failed; append "coarse" and/or
    #    "fine" to stages: with both in a full run, `csr bench` also runs the Table I ablation.

    # 6. fuse: map elements from the aligned trips (III-E). Naive fusion until the fuse stage exists.
    t1 = time.perf_counter()
    features = fuse_naively(trips, poses_by_key, params.keyframe_spacing_m)
    stages.append("naive_fusion")
    timings_s["fuse"] = time.perf_counter() - t1

    # 7. validate: automatic validation of alignment and map.   -- not there yet
    return Reconstruction(
        origin_lat=frame.origin_lat,
        origin_lon=frame.origin_lon,
        poses_xyyaw_world=poses_by_key,
        map_features=features,
        failed=failed,
        diagnostics={
            "method": Method.PIPELINE.value,
            "stages": stages,
            "timings_s": timings_s,
            "coarse": params.coarse,
            "fine": params.fine,
        },
    )
