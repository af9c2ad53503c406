"""The per-tile jobs: ``align_tile`` (coarse then fine alignment of the tile's trips, paper III-D)
and ``merge_tile`` (topology generation and validation, then a new tile version, III-E).

``align_tile z/x/y``
    Takes the tile's trips (``trip_tiles``): all of them the first time, afterwards only those not
    yet aligned here. Each trip's frames in the tile or its halo become pieces
    (``csr_core.tiling``), aligned together against the pre-built map of the tile and its halo
    (the live map, ``P_sub-pre``). Stores per trip and tile the aligned poses, residuals and the
    trip's instances moved with its alignment (``trip_tile_alignments``, upserted: a re-run
    overwrites), the accepted match pairs, marks the trips' tile rows processed, queues a
    ``merge_tile`` for the tile, and finishes every trip whose tiles are now all aligned: its
    final poses (``trip_poses``, blended across tile edges) and status ``aligned`` (or ``failed``
    with the reason when a tile could not align it). All in one transaction with the job's end.

``merge_tile z/x/y``
    Fuses the tile's aligned, not yet merged trips into the tile's road structure: incrementally
    (``update_topology``) from the state of the tile's latest version, or from scratch the first
    time (or when a trip was re-aligned, or a trip of the state erased: ``services.erasure``). Only
    the new version and the live one keep their topology state (:func:`drop_older_states`).
    Features are clipped to the tile and written as a new version
    (``services.db.versions.write_tile_version``) with the expected version read at the start: a concurrent merge of the same tile makes this one retry (:class:`RetryJob`). The
    version is published unless the validator's tile quality is below
    ``Settings.publish_min_quality``: then it is a candidate for review.
"""

from __future__ import annotations

import io
import logging
import pickle
import time
import zlib
from collections import Counter
from collections.abc import Sequence
from dataclasses import asdict, dataclass, field, replace
from typing import Any

import numpy as np
import shapely
from sqlalchemy import select, update
from sqlalchemy.orm import Session, sessionmaker

from csr_core.alignment import DEFAULT as ALIGNMENT_DEFAULT
from csr_core.alignment import (
    AlignmentResult,
    GnssBiasMessage,
    MatchCorrections,
    PairConstraint,
    PriorMap,
    align_trips,
    bias_message,
)
from csr_core.alignment.corrections import PRIOR_KEY
from csr_core.alignment.submaps import gnss_prior_poses_xyyaw
from csr_core.errors import AlignmentFailed
from csr_core.geo import LocalFrame, tile_bounds_lonlat
from csr_core.single_trip import DEFAULT as SINGLE_TRIP_DEFAULT
from csr_core.single_trip.integrity import check_aligned_poses
from csr_core.tiling import (
    assemble_poses,
    blend_weight,
    crop_reconstruction,
    piece_runs,
    reframe_points,
    reframe_poses,
    reframe_reconstruction,
    signed_distance_m,
    tile_polygon_xy,
)
from csr_core.topology import (
    SUSPECT,
    TopologyResult,
    generate_topology,
    reposition_instances,
    update_topology,
)
from csr_core.topology.absolute_uncertainty import TripBias, trip_biases, with_absolute_uncertainty
from csr_core.topology.degraded import hold_back_degraded
from csr_core.types import DividerStyle, ElementType, MapFeature, TripReconstruction
from csr_core.upload import decode_trip
from services.db import repo, versions
from services.db.engine import read_only
from services.db.models import (
    Correction,
    DirtyTile,
    Job,
    MatchPair,
    TileVersion,
    Trip,
    TripPoses,
    TripReconstructionRecord,
    TripTile,
    TripTileAlignment,
    utcnow,
)
from services.reconstructions import (
    ALGORITHM_VERSION,
    _plain_json,
    decode_arrays,
    instance_from_json,
    instance_json,
    noise_from_json,
    noise_json,
)
from services.settings import Settings
from services.tile_frames import Side, tile_frame
from services.upload_formats import stored_document
from workers.dispatch import neighbours_to_wait_for

log = logging.getLogger(__name__)

NO_OVERLAP = "no_overlap"  # nothing else in the tile to align with: the trip keeps its own poses
TOPOLOGY_STATE_VERSION = "topology-2"  # bump when TopologyResult's pickled form changes


# flags that hold a merge back for review (``SUSPECT`` but low support and gaps: see tile_quality)
GATE_FLAGS = SUSPECT - {"low_support", "gap"}


class RetryJob(Exception):
    """A transient conflict (another job wrote the tile first): the job is queued again."""

    counts_as_attempt = True


class WaitForNeighbours(RetryJob):
    """A tile's first alignment waits for a neighbour's first version (queued again; it did no
    work, so the attempt is not counted)."""

    counts_as_attempt = False


NEIGHBOUR_WAIT_S = 0.5  # pause before a waiting job goes back to the queue (no busy loop)


# --- align_tile -----------------------------------------------------------------------------------


@dataclass
class TripAlignment:
    """What one align job made of one trip in its tile (tile frame)."""

    trip_pk: str
    frame_indices: np.ndarray
    poses_xyyaw: np.ndarray
    weights: np.ndarray
    residuals_m: np.ndarray
    instances: list[dict]
    noise: dict
    failed_reason: str | None


@dataclass
class AlignTileResult:
    frame: LocalFrame
    full: bool = False
    trips: list[TripAlignment] = field(default_factory=list)
    match_pairs: list[dict] = field(default_factory=list)
    diagnostics: dict = field(default_factory=dict)


def compute_align_tile(
    session_factory: sessionmaker[Session], settings: Settings, z: int, x: int, y: int, *, full: bool = False
) -> AlignTileResult:
    """``full``: re-align every trip of the tile with the map team's corrections (a ``correct_tile``
    job), against the neighbouring tiles' map only (the tile's own map is what is being redone)."""
    frame = tile_frame(z, x, y)
    with read_only(session_factory)() as session:
        waiting = neighbours_to_wait_for(session, z, x, y) if not full and settings.tile_checkerboard else []
        if waiting:
            session.close()
            time.sleep(NEIGHBOUR_WAIT_S)
            raise WaitForNeighbours(f"first alignment waits for the first version of {', '.join(waiting)}")
        has_version = versions.has_version(session, z=z, x=x, y=y) and not full
        rows = session.execute(
            select(TripTile.trip_pk, TripTile.processed_job_id)
            .join(Trip, Trip.id == TripTile.trip_pk)
            .where(TripTile.z == z, TripTile.x == x, TripTile.y == y, Trip.status != "failed")
            .order_by(Trip.received_at, Trip.id)
        ).all()
        trip_pks = [pk for pk, done in rows if not (has_version and done)]
        loaded = {pk: _load_reconstruction(session, pk, frame) for pk in trip_pks}
        recons = {pk: r for pk, r in loaded.items() if r is not None}
        prior = _prior_map(session, z, x, y, frame, settings.tile_halo_m, exclude_own=full)
        constraints = corrections_of_tile(session, z, x, y) if full else ([], [])
        messages = bias_messages_of(session, recons, z, x, y, frame)
    result = AlignTileResult(frame, full=full)
    if not recons:
        return result
    human_corrected = any(len(c) for c in constraints)
    polygon = tile_polygon_xy(z, x, y, frame)
    pieces: list[TripReconstruction] = []
    piece_of: dict[str, tuple[str, int, np.ndarray]] = {}  # piece key -> trip pk, start, signed distances
    for pk, recon in recons.items():
        signed = signed_distance_m(recon.poses_xyyaw_world[:, :2], polygon)
        for start, stop in piece_runs(signed, settings.tile_halo_m):
            piece = crop_reconstruction(recon, start, stop, suffix=f"@{start}")
            pieces.append(piece)
            piece_of[piece.trip.key] = (pk, start, signed[start:stop])
    corrections = piece_constraints(constraints, piece_of, {p.trip.key: p.trip.n_frames for p in pieces})
    piece_messages = {key: messages[pk] for key, (pk, _, _) in piece_of.items() if messages.get(pk)}
    alignment = _align(pieces, prior, corrections, piece_messages)
    per_trip: dict[str, list] = {pk: [] for pk in recons}
    reverted: dict[str, str] = {}
    for piece in pieces:
        pk, start, signed = piece_of[piece.trip.key]
        poses, weights, residuals, moved, failed = piece_outcome(
            piece, alignment, signed, settings.tile_halo_m
        )
        if failed is None and weights.any():
            # a piece the alignment moved farther from its own GNSS than its error model allows
            # keeps its single-trip poses and has no say on the trip's (like an unaligned one);
            # under the map team's corrections the aligned poses stand, and the finding is recorded
            kept, why = check_aligned_poses(
                piece.trip,
                piece.poses_xyyaw_world,
                poses,
                frame,
                SINGLE_TRIP_DEFAULT,
                float(piece.diagnostics.get("gnss_latency_s", 0.0)),
                piece.gnss_inlier,
            )
            if why is not None and human_corrected:
                reverted[pk] = why.replace("single-trip poses kept", "kept under the map team's corrections")
            elif why is not None:
                reverted[pk] = why
                poses, weights = kept, np.zeros_like(weights)
                moved = reposition_instances(piece.instances, piece.poses_xyyaw_world, poses)
        per_trip[pk].append((start, poses, weights, residuals, moved, failed))
    for pk, parts in per_trip.items():
        if not parts:
            continue  # only a short run here: its frames follow the neighbouring tiles' alignment
        n = [len(p[1]) for p in parts]
        reasons = [p[5] for p in parts if p[5]]
        result.trips.append(
            TripAlignment(
                trip_pk=pk,
                frame_indices=np.concatenate(
                    [np.arange(p[0], p[0] + k) for p, k in zip(parts, n, strict=True)]
                ),
                poses_xyyaw=np.concatenate([p[1] for p in parts]),
                weights=np.concatenate([p[2] for p in parts]),
                residuals_m=np.concatenate([np.asarray(p[3], float) for p in parts]),
                instances=[instance_json(i) for p in parts for i in p[4]],
                noise=_plain_json(noise_json(recons[pk].noise)),
                # only when no piece here could be aligned; a failed piece among aligned ones just has
                # no weight (its frames follow the aligned ones: ``assemble_poses``)
                failed_reason="; ".join(reasons) if len(reasons) == len(parts) else None,
            )
        )
        if reasons and len(reasons) < len(parts):
            log.info(
                "tile %d/%d/%d: trip %s: %d of %d pieces not aligned (%s)",
                z,
                x,
                y,
                pk,
                len(reasons),
                len(parts),
                reasons[0],
            )
    for rec in alignment.match_pairs:
        if not rec.pose_graph_inlier:
            continue
        record = _plain_json(asdict(rec))
        trip_i = piece_of.get(rec.trip_key_i, (None,))[0]
        trip_j = piece_of.get(rec.trip_key_j, (None,))[0]
        result.match_pairs.append(
            {
                "trip_pk_i": trip_i,
                "trip_pk_j": trip_j,
                "confidence": float(rec.confidence),
                "residual_rms_m": float(rec.residual_rms_m),
                "record": record,
            }
        )
    result.diagnostics = {
        "pieces": len(pieces),
        "prior_features": len(prior.features) if prior else 0,
        "alignment_reverted": reverted,
        "bias_messages": sum(len(m) for m in messages.values()),
        "timings": alignment.diagnostics.get("timings", {}),
    }
    return result


def piece_outcome(piece: TripReconstruction, alignment: AlignmentResult, signed_m: np.ndarray, halo_m: float):
    """What a tile keeps of one aligned piece: ``(poses, blend weights, residuals, instances moved
    with the poses, failure reason or None)``.

    A piece with nothing to align with (``no_overlap``) keeps its own poses; so does a piece that
    no consistent registration ties to the others here (failed). Neither has a say on the trip's
    poses (weight 0): its frames follow the trip's aligned pieces and tiles (``assemble_poses``;
    the single-trip poses where no tile aligned the trip). A piece that met no other trip in one
    tile kept full weight before, and pulled the trip back to its own GNSS there, where the
    whole-batch graph carries the offset learnt elsewhere along the trip (in-process on 10 x 1 km
    fleets, rural ATE 1.44 -> 1.36 m, highway 1.37 -> 1.33 m; urban and Karlsruhe the same). Either
    way its elements stay in the map where its poses put them: this tile cannot tell whether the
    trip is aligned elsewhere (``csr reconstruct`` leaves out only a trip that fails everywhere),
    and the fusion's robust fit and the validator judge them."""
    key = piece.trip.key
    reason = alignment.failed.get(key)
    failed = reason if reason is not None and not reason.startswith(NO_OVERLAP) else None
    if failed:
        poses = alignment.diagnostics.get("unaligned_poses", {}).get(key, piece.poses_xyyaw_world)
    elif reason is not None:
        poses = piece.poses_xyyaw_world
    else:
        poses = alignment.poses_xyyaw_world[key]
    residuals = alignment.frame_residuals_m.get(key, np.full(len(poses), np.nan))
    weights = np.zeros(len(poses)) if reason is not None else blend_weight(signed_m, halo_m)
    moved = reposition_instances(piece.instances, piece.poses_xyyaw_world, poses)
    return poses, weights, residuals, moved, failed


def _align(
    pieces: Sequence[TripReconstruction],
    prior: PriorMap | None,
    corrections: MatchCorrections | None = None,
    bias_messages: dict[str, list[GnssBiasMessage]] | None = None,
) -> AlignmentResult:
    if not pieces:
        return AlignmentResult({}, {}, (), {})
    try:
        return align_trips(pieces, prior_map=prior, corrections=corrections, bias_messages=bias_messages)
    except AlignmentFailed as exc:  # nothing to align with (one piece, no map): each keeps its own poses
        return AlignmentResult({}, {p.trip.key: f"{NO_OVERLAP}: {exc}" for p in pieces}, (), {})


def _load_reconstruction(session: Session, trip_pk: str, frame: LocalFrame) -> TripReconstruction | None:
    row = session.get(TripReconstructionRecord, (trip_pk, ALGORITHM_VERSION))
    upload = repo.raw_upload(session, trip_pk=trip_pk)
    if row is None or upload is None:
        return None
    trip = decode_trip(stored_document(upload.encoding, upload.body))
    recon = reconstruction_from_row(row, trip)
    return reframe_reconstruction(recon, LocalFrame(row.origin_lat, row.origin_lon), frame)


def reconstruction_from_row(row: TripReconstructionRecord, trip) -> TripReconstruction:
    arrays = decode_arrays(row.arrays)
    return TripReconstruction(
        trip=trip,
        poses_xyyaw_world=arrays["poses_xyyaw_world"],
        pose_sigma_xy_m=arrays["pose_sigma_xy_m"].astype(float),
        keyframe_indices=arrays["keyframe_indices"].astype(np.int64),
        instances=tuple(instance_from_json(i) for i in row.instances),
        noise=noise_from_json(row.noise),
        gnss_inlier=arrays["gnss_inlier"],
        diagnostics=dict(row.diagnostics or {}),
        white_poses_xyyaw_world=arrays.get("white_poses_xyyaw_world"),
    )


def bias_messages_of(
    session: Session, recons: dict[str, TripReconstruction], z: int, x: int, y: int, frame: LocalFrame
) -> dict[str, list[GnssBiasMessage]]:
    """What the other tiles that aligned these trips found of each one's GNSS bias (by trip pk):
    one message per trip and tile, from the tile's aligned poses against the trip's single-trip
    poses (``recons``, in ``frame``) weighted by the tile's blend weights, and the number of trips
    that tile tied together (``csr_core.alignment.bias_messages``). Frames a tile did not tie to
    other trips have no weight (``piece_outcome``) and say nothing of the bias (a message "no
    shift" from a ``no_overlap`` piece's own poses held trips back to their own GNSS: in-process
    on five 10 x 1 km fleets, rural ATE 1.42 -> 1.46 m and highway 1.38 -> 1.42 m with them)."""
    if not recons:
        return {}
    tiles = set(
        session.execute(
            select(TripTileAlignment.z, TripTileAlignment.x, TripTileAlignment.y).where(
                TripTileAlignment.trip_pk.in_(list(recons)), TripTileAlignment.failed_reason.is_(None)
            )
        ).all()
    )
    tiles.discard((z, x, y))
    out: dict[str, list[GnssBiasMessage]] = {}
    for tz, tx, ty in sorted(tuple(t) for t in tiles):
        # every trip the tile aligned, each decoded once: the count of trips it tied together
        # (any weight) and the messages of the trips asked about
        rows = session.scalars(
            select(TripTileAlignment).where(
                TripTileAlignment.z == tz,
                TripTileAlignment.x == tx,
                TripTileAlignment.y == ty,
                TripTileAlignment.failed_reason.is_(None),
            )
        ).all()
        decoded = [(r, decode_arrays(r.arrays)) for r in rows]
        n_tied = sum(1 for _, arrays in decoded if arrays["weights"].any())
        for r, arrays in decoded:
            recon = recons.get(r.trip_pk)
            idx = arrays["frame_indices"].astype(np.int64)
            if recon is None or len(idx) == 0 or idx.max() >= recon.trip.n_frames:
                continue
            aligned = reframe_poses(arrays["poses_xyyaw"], LocalFrame(r.origin_lat, r.origin_lon), frame)
            # the bias is the shift from the poses e^g holds the trip's sub-maps at
            prior = gnss_prior_poses_xyyaw(recon, ALIGNMENT_DEFAULT.gnss_prior_from_white_solve)
            msg = bias_message(
                recon.trip.timestamps_s[idx],
                prior[idx, :2],
                aligned[:, :2],
                arrays["weights"],
                n_tied,
                ALIGNMENT_DEFAULT,
            )
            if msg is not None:
                out.setdefault(r.trip_pk, []).append(msg)
    return out


def _prior_map(
    session: Session, z: int, x: int, y: int, frame: LocalFrame, halo_m: float, exclude_own: bool = False
) -> PriorMap | None:
    """The live map of the tile and its halo (neighbouring tiles' features near the edge);
    ``exclude_own``: the neighbours' only."""
    west, south, east, north = tile_bounds_lonlat(z, x, y)
    lat = np.radians((south + north) / 2)
    dlat = halo_m / 111_320.0
    dlon = halo_m / (111_320.0 * max(np.cos(lat), 1e-6))
    features = versions.features_in_bbox(
        session, bbox_lonlat=(west - dlon, south - dlat, east + dlon, north + dlat)
    )
    if exclude_own:
        features = [f for f in features if not f.feature_id.startswith(f"{z}-{x}-{y}-")]
    mapped = [f for f in (_to_map_feature(v, frame) for v in features) if f is not None]
    return PriorMap(tuple(mapped)) if mapped else None


def _to_map_feature(v: versions.VersionFeature, frame: LocalFrame) -> MapFeature | None:
    etype = ElementType(v.type)
    geom = v.geometry
    coords = np.asarray(geom.exterior.coords if etype.is_polygon else geom.coords, float)[:, :2]
    if etype.is_polygon:
        coords = coords[:-1]
    if len(coords) < 2:
        return None
    return MapFeature(
        etype,
        frame.to_local(coords),
        DividerStyle(v.style) if v.style else None,
        v.feature_id,
        dict(v.properties),
    )


def persist_align_tile(
    session: Session, settings: Settings, job_id: str, z: int, x: int, y: int, result: AlignTileResult
) -> None:
    now = utcnow()
    # a trip erased while the tile aligned (services.erasure) leaves nothing behind
    alive = set(session.scalars(select(Trip.id).where(Trip.id.in_([ta.trip_pk for ta in result.trips]))))
    result.trips = [ta for ta in result.trips if ta.trip_pk in alive]
    result.match_pairs = [
        mp
        for mp in result.match_pairs
        if all(mp.get(k) is None or mp.get(k) in alive for k in ("trip_pk_i", "trip_pk_j"))
    ]
    for ta in result.trips:
        values = {
            "job_id": job_id,
            "origin_lat": result.frame.origin_lat,
            "origin_lon": result.frame.origin_lon,
            "arrays": _npz(
                frame_indices=ta.frame_indices.astype(np.int32),
                poses_xyyaw=ta.poses_xyyaw,
                weights=ta.weights.astype(np.float32),
                residuals_m=ta.residuals_m.astype(np.float32),
            ),
            "instances": ta.instances,
            "noise": ta.noise,
            "failed_reason": ta.failed_reason,
            "merged_version_id": None,
            "created_at": now,
        }
        row = session.get(TripTileAlignment, (ta.trip_pk, z, x, y))
        if row is None:
            session.add(TripTileAlignment(trip_pk=ta.trip_pk, z=z, x=x, y=y, **values))
        else:
            for k, v in values.items():
                setattr(row, k, v)
    _record_alignment_quality(
        session,
        z,
        x,
        y,
        [ta.trip_pk for ta in result.trips],
        result.diagnostics.get("alignment_reverted", {}),
    )
    if result.full:  # the tile was re-aligned as a whole: its earlier pairs no longer hold
        session.execute(
            update(MatchPair)
            .where(
                MatchPair.z == z,
                MatchPair.x == x,
                MatchPair.y == y,
                MatchPair.job_id != job_id,
                MatchPair.status.in_(("active", "added")),
            )
            .values(status="superseded")
        )
    for mp in result.match_pairs:
        status = "added" if mp["record"].get("human") else "active"
        session.add(
            MatchPair(id=repo.new_id(), z=z, x=x, y=y, job_id=job_id, status=status, created_at=now, **mp)
        )
    # the trips this job takes: only they can become complete now
    taken = set(
        session.scalars(
            select(TripTile.trip_pk).where(
                TripTile.z == z, TripTile.x == x, TripTile.y == y, TripTile.processed_job_id.is_(None)
            )
        )
    )
    taken |= {ta.trip_pk for ta in result.trips}
    session.execute(
        update(TripTile)
        .where(TripTile.z == z, TripTile.x == x, TripTile.y == y, TripTile.processed_job_id.is_(None))
        .values(processed_job_id=job_id)
    )
    dirty = session.scalars(
        select(DirtyTile).where(DirtyTile.z == z, DirtyTile.x == x, DirtyTile.y == y).with_for_update()
    ).one_or_none()
    if dirty is not None and dirty.job_id == job_id:
        session.delete(dirty)
    if result.trips:
        repo.add_job(session, kind="merge_tile", subject=f"{z}/{x}/{y}")
    for pk in sorted(taken):
        finish_trip_if_complete(session, pk, job_id)


def _record_alignment_quality(
    session: Session, z: int, x: int, y: int, trip_pks: Sequence[str], reverted: dict[str, str]
) -> None:
    """Each trip's ``alignment_quality`` (``GET /v1/trips/{id}``'s ``quality.alignment``): by tile,
    why this tile kept the trip's single-trip poses (``integrity.check_aligned_poses``); the
    tile's entry cleared when it aligned the trip cleanly this time."""
    if not trip_pks:
        return
    tile = f"{z}/{x}/{y}"
    r = TripReconstructionRecord
    rows = session.scalars(
        select(r)
        .where(r.trip_pk.in_(list(trip_pks)), r.algorithm_version == ALGORITHM_VERSION)
        .with_for_update()
    ).all()
    for row in rows:
        diagnostics = dict(row.diagnostics or {})
        by_tile = dict(diagnostics.get("alignment_quality") or {})
        if row.trip_pk in reverted:
            by_tile[tile] = reverted[row.trip_pk]
        elif tile in by_tile:
            del by_tile[tile]
        else:
            continue
        diagnostics["alignment_quality"] = by_tile or None
        row.diagnostics = diagnostics


def finish_trip_if_complete(session: Session, trip_pk: str, job_id: str) -> bool:
    """Once every tile of a trip has aligned it: its final poses and status. The trip row is locked
    first, so of two tile jobs finishing at once the later one sees both tiles done."""
    # FOR NO KEY UPDATE: serialises the finishers of one trip but not the KEY SHARE locks that the
    # foreign keys of other jobs' rows take on it (FOR UPDATE deadlocked two tile jobs that had
    # each written a row of the other's trip)
    trip = session.scalars(
        select(Trip).where(Trip.id == trip_pk).with_for_update(key_share=True)
    ).one_or_none()
    if trip is None or trip.status not in ("processing", "aligned"):
        return False
    pending = session.scalar(
        select(TripTile.trip_pk)
        .where(TripTile.trip_pk == trip_pk, TripTile.processed_job_id.is_(None))
        .limit(1)
    )
    if pending is not None:
        return False
    row = session.get(TripReconstructionRecord, (trip_pk, ALGORITHM_VERSION))
    if row is None:
        return False
    own = LocalFrame(row.origin_lat, row.origin_lon)
    smoothed = decode_arrays(row.arrays)["poses_xyyaw_world"]
    contributions, reasons = [], []
    for a in session.scalars(select(TripTileAlignment).where(TripTileAlignment.trip_pk == trip_pk)):
        arrays = decode_arrays(a.arrays)
        poses = reframe_poses(arrays["poses_xyyaw"], LocalFrame(a.origin_lat, a.origin_lon), own)
        contributions.append((arrays["frame_indices"].astype(np.int64), poses, arrays["weights"]))
        if a.failed_reason:
            reasons.append(f"tile {a.z}/{a.x}/{a.y}: {a.failed_reason}")
    poses, aligned = assemble_poses(smoothed, contributions)
    if aligned.any():  # a tile that could not align it is bridged by the others' correction
        reasons = []
    upload = repo.raw_upload(session, trip_pk=trip_pk)
    t = (
        decode_trip(stored_document(upload.encoding, upload.body)).timestamps_s
        if upload is not None
        else None
    )
    if t is None or len(t) != len(poses):
        return False
    lonlat = own.to_lonlat(poses[:, :2])
    blob = _npz(t=t, lat=lonlat[:, 1], lon=lonlat[:, 0], heading_deg=own.heading_deg(poses[:, 2], lonlat))
    existing = session.get(TripPoses, trip_pk)
    if existing is None:
        session.add(TripPoses(trip_pk=trip_pk, job_id=job_id, arrays=blob, created_at=utcnow()))
    else:
        existing.job_id, existing.arrays, existing.created_at = job_id, blob, utcnow()
    if reasons:
        trip.status, trip.error = "failed", "alignment failed: " + "; ".join(reasons)
    else:
        trip.status, trip.error = "aligned", None
    trip.updated_at = utcnow()
    return True


# --- corrections ----------------------------------------------------------------------------------


def corrections_of_tile(
    session: Session, z: int, x: int, y: int
) -> tuple[list[tuple[Side, Side]], list[tuple[Side, Side, tuple | None]]]:
    """The tile's corrections in force (not undone) as rejected and added pairs of trip frames."""
    rejected, added = [], []
    rows = session.scalars(
        select(Correction)
        .where(Correction.z == z, Correction.x == x, Correction.y == y, Correction.undone_at.is_(None))
        .order_by(Correction.created_at)
    )
    for c in rows:
        p = c.payload
        if c.kind == "reject_pair":
            rejected.append(((p["trip_i"], tuple(p["frames_i"])), (p["trip_j"], tuple(p["frames_j"]))))
        elif c.kind == "add_pair":
            offset = tuple(p["offset_xyyaw"]) if p.get("offset_xyyaw") is not None else None
            added.append(((p["trip_i"], tuple(p["frames_i"])), (p["trip_j"], tuple(p["frames_j"])), offset))
    return rejected, added


def piece_constraints(
    constraints, piece_of: dict[str, tuple[str, int, np.ndarray]], n_frames: dict[str, int]
) -> MatchCorrections | None:
    """Stored corrections (trip frames) -> constraints on this job's pieces (piece keys and frames)."""
    rejected, added = constraints
    if not rejected and not added:
        return None

    def sides(side: Side) -> list[tuple[str, tuple[int, int]]]:
        pk, (a, b) = side
        if pk is None:
            return [(PRIOR_KEY, (0, 0))]
        out = []
        for key, (piece_pk, start, _) in piece_of.items():
            lo, hi = max(a - start, 0), min(b - start, n_frames[key] - 1)
            if piece_pk == pk and lo <= hi:
                out.append((key, (lo, hi)))
        return out

    rej = tuple(
        PairConstraint(ki, fi, kj, fj) for si, sj in rejected for ki, fi in sides(si) for kj, fj in sides(sj)
    )
    add = tuple(
        PairConstraint(ki, fi, kj, fj, off)
        for si, sj, off in added
        for ki, fi in sides(si)[:1]
        for kj, fj in sides(sj)[:1]
    )
    return MatchCorrections(rej, add)


# --- merge_tile -----------------------------------------------------------------------------------


@dataclass
class MergeTileResult:
    expected_latest: int | None
    features: list[versions.VersionFeature]
    trips: list[str]  # the trips merged: their alignment rows get the new version
    quality: dict
    state: bytes | None
    frame: LocalFrame
    publish: bool
    nothing_to_do: bool = False
    corrections: list[str] = field(default_factory=list)  # "<id>" applied, "<id>:undo" undone
    reason: str = "merge"
    erased: list[str] = field(default_factory=list)  # trips of the tile's state that no longer exist here


def compute_merge_tile(
    session_factory: sessionmaker[Session], settings: Settings, z: int, x: int, y: int
) -> MergeTileResult:
    frame = tile_frame(z, x, y)
    with read_only(session_factory)() as session:
        latest = versions.latest_version(session, z=z, x=x, y=y)
        expected = latest.version if latest is not None else None
        state = _load_state(latest)
        stmt = select(TripTileAlignment).where(
            TripTileAlignment.z == z, TripTileAlignment.x == x, TripTileAlignment.y == y
        )
        if state is not None:  # incremental: only what is new is read
            stmt = stmt.where(TripTileAlignment.merged_version_id.is_(None))
        rows = session.scalars(stmt.order_by(TripTileAlignment.created_at)).all()
        erased = trips_gone_from_state(session, state, z, x, y)
        started = (
            dict(
                session.execute(
                    select(Trip.id, Trip.started_at).where(Trip.id.in_([r.trip_pk for r in rows]))
                ).all()
            )
            if rows
            else {}
        )
        new = [r for r in rows if r.merged_version_id is None]
        everything: Sequence[TripTileAlignment] = list(rows)
        inputs_new = {r.trip_pk: _alignment_inputs(r, frame) for r in new}
        inputs_all = {r.trip_pk: _alignment_inputs(r, frame) for r in everything} if state is None else {}
        pairs = session.scalars(
            select(MatchPair).where(
                MatchPair.z == z,
                MatchPair.x == x,
                MatchPair.y == y,
                MatchPair.status.in_(("active", "added")),
            )
        ).all()
        match_pairs = [p.record for p in pairs]
        applied = pending_corrections(session, z, x, y)
    if not new and not erased:
        return MergeTileResult(expected, [], [], {}, None, frame, False, nothing_to_do=True)
    reason = "merge"
    if applied:
        reason = "correction" if any(not a.endswith(":undo") for a in applied) else "undo correction"
    if erased:  # trips erased (services.erasure): rebuilt from the trips that remain
        reason = "erasure"
    instances = {pk: v[0] for pk, v in inputs_new.items()}
    noise = {pk: v[1] for pk, v in inputs_new.items()}
    paths = {pk: v[2] for pk, v in inputs_new.items()}
    times = {pk: started.get(pk, "") for pk in inputs_new}
    records = [_PairView(r) for r in match_pairs]
    known = (
        set()
        if state is None
        else ({m.trip_key for mem in state.members.values() for m in mem} | set(state.trip_points))
    )
    if state is not None and not (set(instances) & known) and not erased:
        topology = update_topology(
            state, instances, noise, trip_times=times, match_pairs=records, paths_xy_per_trip=paths
        )
    else:  # the first version, or trips re-aligned: rebuild from every aligned trip, ids continue
        if state is not None:
            with read_only(session_factory)() as session:
                everything = session.scalars(
                    select(TripTileAlignment).where(
                        TripTileAlignment.z == z, TripTileAlignment.x == x, TripTileAlignment.y == y
                    )
                ).all()
                inputs_all = {r.trip_pk: _alignment_inputs(r, frame) for r in everything}
                started = dict(
                    session.execute(
                        select(Trip.id, Trip.started_at).where(Trip.id.in_(list(inputs_all)))
                    ).all()
                )
        if not inputs_all:  # every trip of the tile erased: an empty version
            quality = {**tile_quality([]), "seams": {}, "held_back": {}}
            return MergeTileResult(
                expected, [], [], quality, None, frame, True, reason=reason, erased=sorted(erased)
            )
        topology = generate_topology(
            {pk: v[0] for pk, v in inputs_all.items()},
            {pk: v[1] for pk, v in inputs_all.items()},
            previous=state,
            trip_times={pk: started.get(pk, "") for pk in inputs_all},
            match_pairs=records,
            paths_xy_per_trip={pk: v[2] for pk, v in inputs_all.items()},
        )
    behind = {t for f in (*topology.features, *topology.suppressed) for t in f.properties.get("trips", ())}
    behind |= set(topology.trip_paths) | set(topology.trip_points)
    with session_factory() as session:
        degraded = degraded_trips(session, behind)
        biases = trip_biases_of(session, behind)
    if degraded:  # features of degraded trips flagged; those only they support held back (like ghosts)
        kept, held = hold_back_degraded(topology.features, topology.suppressed, degraded)
        topology = replace(topology, features=kept, suppressed=held)
    # each element's absolute sigma: its relative spread and its trips' GNSS biases (Eq. 1)
    paths = {**topology.trip_points, **topology.trip_paths}
    topology = replace(
        topology,
        features=tuple(with_absolute_uncertainty(topology.features, biases, paths)),
        suppressed=tuple(with_absolute_uncertainty(topology.suppressed, biases, paths)),
    )
    features = clip_to_tile(topology.features, frame, z, x, y)
    with read_only(session_factory)() as session:
        seams = check_seams(session, features, frame, z, x, y)
    quality = {
        **tile_quality(features),
        "seams": seams,
        "held_back": held_back_counts(clip_to_tile(topology.suppressed, frame, z, x, y)),
    }
    return MergeTileResult(
        expected_latest=expected,
        features=features,
        trips=sorted(inputs_all) if erased else sorted(inputs_new),
        quality=quality,
        state=zlib.compress(pickle.dumps((TOPOLOGY_STATE_VERSION, frame, topology), protocol=5)),
        frame=frame,
        publish=quality["score"] >= settings.publish_min_quality,
        corrections=applied,
        reason=reason,
        erased=sorted(erased),
    )


def trips_gone_from_state(session: Session, state: TopologyResult | None, z: int, x: int, y: int) -> set[str]:
    """The trips the tile's topology state was built from that have no alignment row in the tile
    any more (erased, or reprocessed onto other tiles): the next merge rebuilds without them."""
    if state is None:
        return set()
    known = {m.trip_key for mem in state.members.values() for m in mem} | set(state.trip_points)
    if not known:
        return set()
    present = set(
        session.scalars(
            select(TripTileAlignment.trip_pk).where(
                TripTileAlignment.z == z, TripTileAlignment.x == x, TripTileAlignment.y == y
            )
        )
    )
    return {str(k) for k in known} - present


def degraded_trips(session: Session, trip_pks: set[str]) -> set[str]:
    """The trips among ``trip_pks`` whose single-trip poses failed the integrity test even after
    the repair (``quality.verdict == "degraded"`` in their reconstruction's diagnostics)."""
    if not trip_pks:
        return set()
    r = TripReconstructionRecord
    rows = session.execute(
        select(r.trip_pk, r.diagnostics).where(
            r.trip_pk.in_(sorted(trip_pks)), r.algorithm_version == ALGORITHM_VERSION
        )
    ).all()
    return {pk for pk, diag in rows if ((diag or {}).get("quality") or {}).get("verdict") == "degraded"}


def trip_biases_of(session: Session, trip_pks: set[str]) -> dict[str, TripBias]:
    """The GNSS bias (sigma, correlation length) of each trip among ``trip_pks`` whose current
    reconstruction's diagnostics hold one; the others are absent (Eq. 1 of
    ``topology.absolute_uncertainty`` counts a trip that saw an element with the unknown sigma)."""
    if not trip_pks:
        return {}
    r = TripReconstructionRecord
    rows = session.execute(
        select(r.trip_pk, r.diagnostics).where(
            r.trip_pk.in_(sorted(trip_pks)), r.algorithm_version == ALGORITHM_VERSION
        )
    ).all()
    return trip_biases({pk: diag or {} for pk, diag in rows})


class _PairView:
    """A stored match-pair record read like ``MatchPairRecord`` (what validation reads)."""

    def __init__(self, record: dict[str, Any]) -> None:
        self.__dict__.update(record)


def _alignment_inputs(row: TripTileAlignment, frame: LocalFrame):
    arrays = decode_arrays(row.arrays)
    src = LocalFrame(row.origin_lat, row.origin_lon)
    instances = [instance_from_json(i) for i in row.instances]
    if src != frame:
        instances = [
            replace(i, points_xy_world=reframe_points(i.points_xy_world, src, frame)) for i in instances
        ]
    poses = reframe_poses(arrays["poses_xyyaw"], src, frame)
    return instances, noise_from_json(row.noise), poses[:, :2]


def _load_state(latest: TileVersion | None) -> TopologyResult | None:
    if latest is None or latest.state is None:
        return None
    try:
        tag, _frame, topology = pickle.loads(zlib.decompress(latest.state))
    except Exception:  # an unreadable or older state: rebuild
        log.warning(
            "tile version %s: topology state unreadable (the next merge rebuilds the topology)",
            latest.id,
            exc_info=True,
        )
        return None
    return topology if tag == TOPOLOGY_STATE_VERSION else None


def clip_to_tile(
    features: Sequence[MapFeature], frame: LocalFrame, z: int, x: int, y: int
) -> list[versions.VersionFeature]:
    """The tile's part of each feature, in lon/lat; ids ``<z>-<x>-<y>-<topology id>``. A polygon
    belongs to the tile holding its centroid (never cut); a line is cut at the tile's edges."""
    west, south, east, north = tile_bounds_lonlat(z, x, y)
    box = shapely.box(west, south, east, north)
    out: list[versions.VersionFeature] = []
    for f in features:
        lonlat = frame.to_lonlat(f.points_xy_world)
        props = {k: v for k, v in _plain_json(f.properties).items() if k != "trips"}
        props["n_flags"] = len(props.get("flags") or [])  # a scalar: vector tiles drop lists
        fid = f"{z}-{x}-{y}-{f.feature_id}"
        style = f.style.value if f.style is not None else None
        if f.type.is_polygon:
            if len(lonlat) < 3:
                continue
            poly = shapely.Polygon(lonlat)
            if box.contains(poly.centroid):
                out.append(versions.VersionFeature(fid, f.type.value, style, props, poly))
            continue
        if len(lonlat) < 2:
            continue
        clipped = shapely.clip_by_rect(shapely.LineString(lonlat), west, south, east, north)
        parts = [g for g in getattr(clipped, "geoms", [clipped]) if not g.is_empty and g.length > 0]
        for k, part in enumerate(sorted(parts, key=lambda g: -g.length)):
            out.append(
                versions.VersionFeature(fid if k == 0 else f"{fid}.{k}", f.type.value, style, props, part)
            )
    return out


SEAM_FLOOR_M = 0.10  # two tiles' halves of an element may differ this much whatever their uncertainty
SEAM_SEARCH_M = 2.0  # beyond this the neighbour has no half of this element (it ends at the edge)


def check_seams(
    session: Session, features: list[versions.VersionFeature], frame: LocalFrame, z: int, x: int, y: int
) -> dict[str, Any]:
    """Where a line crosses the tile's edge, its neighbour's half must continue it: the gap between the
    two ends on the edge within ``max(SEAM_FLOOR_M, 3 sigma)`` (sigma: both halves' uncertainty).
    Flags ``seam_gap`` on the features that break it; returns the gaps' statistics."""
    west, south, east, north = tile_bounds_lonlat(z, x, y)
    eps = 5e-8  # stored coordinates are rounded to 1e-8 degrees

    def edge_ends(f: versions.VersionFeature) -> list[np.ndarray]:
        if f.geometry.geom_type != "LineString":
            return []
        coords = np.asarray(f.geometry.coords)[:, :2]
        return [
            p
            for p in (coords[0], coords[-1])
            if min(abs(p[0] - west), abs(p[0] - east), abs(p[1] - south), abs(p[1] - north)) < eps
        ]

    mine = [(f, p) for f in features for p in edge_ends(f)]
    if not mine:
        return {"checked": 0}
    margin = 1e-4  # ~10 m: the neighbours' elements touching this tile's edges
    others = [
        f
        for f in versions.features_in_bbox(
            session, bbox_lonlat=(west - margin, south - margin, east + margin, north + margin)
        )
        if not f.feature_id.startswith(f"{z}-{x}-{y}-")
    ]
    theirs = [(f, p) for f in others for p in edge_ends(f)]
    gaps = []
    for f, p in mine:
        candidates = [(g, q) for g, q in theirs if g.type == f.type]
        if not candidates:
            continue
        here = frame.to_local(p[None])[0]
        dist = np.linalg.norm(frame.to_local(np.array([q for _, q in candidates])) - here, axis=1)
        k = int(np.argmin(dist))
        if dist[k] > SEAM_SEARCH_M:
            continue
        sigma = np.hypot(
            float(f.properties.get("uncertainty_m") or 0.0),
            float(candidates[k][0].properties.get("uncertainty_m") or 0.0),
        )
        gaps.append(float(dist[k]))
        if dist[k] > max(SEAM_FLOOR_M, 3.0 * sigma):
            flags = sorted(set(f.properties.get("flags") or []) | {"seam_gap"})
            f.properties["flags"], f.properties["n_flags"] = flags, len(flags)
    if not gaps:
        return {"checked": 0}
    g = np.asarray(gaps)
    return {
        "checked": len(g),
        "median_gap_m": round(float(np.median(g)), 4),
        "p95_gap_m": round(float(np.percentile(g, 95)), 4),
        "max_gap_m": round(float(g.max()), 4),
        "flagged": int(sum(1 for f, _ in mine if "seam_gap" in (f.properties.get("flags") or []))),
    }


def tile_quality(features: Sequence[versions.VersionFeature]) -> dict[str, Any]:
    """The tile's quality for the publish gate: the share of its features without a flag saying the
    evidence contradicts itself (:data:`GATE_FLAGS`: ``score``), and counts of all flags by kind.
    Low support and gaps are flagged on the features but do not hold a version back: a road seen
    by few trips yet is expected where the fleet has just started."""
    counts: dict[str, int] = {}
    flagged = 0
    for f in features:
        flags = f.properties.get("flags") or []
        if set(flags) & GATE_FLAGS:
            flagged += 1
        for flag in flags:
            kind = str(flag)
            counts[kind] = counts.get(kind, 0) + 1
    n = len(features)
    return {"score": 1.0 - flagged / n if n else 1.0, "n_features": n, "n_flagged": flagged, "flags": counts}


def held_back_counts(held: Sequence[versions.VersionFeature]) -> dict[str, int]:
    """Lines of the tile held back from the version, by type (``TopologyResult.suppressed``: trips
    drove alongside them and did not see them); they stay in the topology state and are published
    once more trips confirm them."""
    return dict(Counter(str(f.type) for f in held))


def held_back_features(version: TileVersion) -> list[versions.VersionFeature] | None:
    """The lines ``version`` held back (``TopologyResult.suppressed`` of its topology state), clipped
    to its tile in lon/lat as the merge clipped them for ``quality["held_back"]`` (same ids, same
    parts); ``None`` when the version has no readable state (written without one, or by an older
    :data:`TOPOLOGY_STATE_VERSION`). Frame: the version's ``origin_lat/lon`` (the merge's frame)."""
    topology = _load_state(version)
    if topology is None:
        return None
    frame = LocalFrame(version.origin_lat, version.origin_lon)
    return clip_to_tile(topology.suppressed, frame, version.z, version.x, version.y)


def persist_merge_tile(
    session: Session, job_id: str, z: int, x: int, y: int, result: MergeTileResult
) -> None:
    if result.nothing_to_do:
        return
    try:
        version = versions.write_tile_version(
            session,
            z=z,
            x=x,
            y=y,
            features=result.features,
            reason=result.reason,
            job_id=job_id,
            trips=result.trips,
            corrections=result.corrections,
            quality=result.quality,
            origin_lat=result.frame.origin_lat,
            origin_lon=result.frame.origin_lon,
            state=result.state,
            publish=result.publish,
            expected_latest=result.expected_latest,
        )
    except versions.VersionConflict as exc:
        raise RetryJob(str(exc)) from exc
    session.execute(
        update(TripTileAlignment)
        .where(
            TripTileAlignment.z == z,
            TripTileAlignment.x == x,
            TripTileAlignment.y == y,
            TripTileAlignment.trip_pk.in_(result.trips),
        )
        .values(merged_version_id=version.id)
    )
    drop_older_states(session, z, x, y, keep=version.id, keep_live=not result.erased)
    for entry in result.corrections:
        correction = session.get(Correction, entry.removesuffix(":undo"))
        if correction is None:
            continue
        if entry.endswith(":undo"):
            correction.payload = {**correction.payload, "undo_version_id": version.id}
        else:
            correction.result_version_id = version.id


def drop_older_states(session: Session, z: int, x: int, y: int, *, keep: int, keep_live: bool) -> None:
    """Drop the topology state of the tile's versions but ``keep`` (the new one, which the next merge
    continues from) and, with ``keep_live``, the live one: each state holds every trip's probe
    points, so keeping them all would grow the tile's storage with the square of its trips. An
    older version's held-back lines then answer 409; rolling back to it rebuilds the next merge
    from scratch. After an erasure (``keep_live`` False) only the new version's state is kept: the
    others hold the erased trips' points."""
    stmt = update(TileVersion).where(
        TileVersion.z == z,
        TileVersion.x == x,
        TileVersion.y == y,
        TileVersion.id != keep,
        TileVersion.state.is_not(None),
    )
    if keep_live:
        head = versions.tile_head(session, z=z, x=x, y=y)
        if head is not None and head.live_version_id is not None:
            stmt = stmt.where(TileVersion.id != head.live_version_id)
    session.execute(stmt.values(state=None).execution_options(synchronize_session=False))


def pending_corrections(session: Session, z: int, x: int, y: int) -> list[str]:
    """The tile's corrections applied or undone by a re-alignment but not yet in a version:
    ``"<id>"`` applied, ``"<id>:undo"`` undone."""
    out = []
    done = set(
        session.scalars(
            select(Job.id).where(
                Job.kind == "correct_tile", Job.subject == f"{z}/{x}/{y}", Job.state == "done"
            )
        )
    )
    for c in session.scalars(
        select(Correction).where(Correction.z == z, Correction.x == x, Correction.y == y)
    ):
        if c.undone_at is None and c.result_version_id is None and c.job_id in done:
            out.append(c.id)
        elif (
            c.undone_at is not None
            and "undo_version_id" not in c.payload
            and c.payload.get("undo_job_id") in done
        ):
            out.append(f"{c.id}:undo")
    return sorted(out)


def _npz(**arrays: np.ndarray) -> bytes:
    buffer = io.BytesIO()
    # mypy checks the **arrays values against allow_pickle: bool too (no key is named so)
    np.savez_compressed(buffer, **{k: np.asarray(v) for k, v in arrays.items()})  # type: ignore[arg-type]
    return buffer.getvalue()
