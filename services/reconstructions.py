"""Single-trip reconstruction results <-> the ``trip_reconstructions`` row (the service's edge of
``csr_core.single_trip``).

Stored form (one row per trip and ``ALGORITHM_VERSION``): poses and instance points are metres in
the trip's region frame, ``csr_core.geo.region_frame_for(first fix)``, whose origin is stored with
them (``LocalFrame(origin_lat, origin_lon).to_lonlat`` re-projects). Every trip starting in the
same zoom-10 tile (~40 km) shares one frame, so alignment can combine trips without re-projecting;
a consumer in another frame re-projects through lon/lat. Arrays go into one
``np.savez_compressed`` blob; instances, noise and diagnostics are JSON.
"""

from __future__ import annotations

import io
from typing import Any

import numpy as np
import orjson

from csr_core.geo import LocalFrame
from csr_core.types import DividerStyle, ElementNoise, ElementType, TripInstance, TripReconstruction

# Bump when single-trip reconstruction changes its results: rows of other versions are kept,
# `csr reprocess --stale` recomputes the trips without a row of this version.
ALGORITHM_VERSION = "single_trip-11"

_POINT_DECIMALS = 3  # millimetres: far below the perception noise


def encode_arrays(recon: TripReconstruction) -> bytes:
    n = recon.trip.n_frames
    inlier = recon.gnss_inlier if recon.gnss_inlier is not None else recon.trip.has_fix
    arrays: dict[str, np.ndarray] = {
        "poses_xyyaw_world": np.asarray(recon.poses_xyyaw_world, np.float64).reshape(n, 3),
        "pose_sigma_xy_m": np.asarray(recon.pose_sigma_xy_m, np.float32).reshape(n),
        "keyframe_indices": np.asarray(recon.keyframe_indices, np.int32),
        "gnss_inlier": np.asarray(inlier, bool).reshape(n),
    }
    if recon.white_poses_xyyaw_world is not None:
        arrays["white_poses_xyyaw_world"] = np.asarray(recon.white_poses_xyyaw_world, np.float64).reshape(
            n, 3
        )
    buffer = io.BytesIO()
    # mypy checks the **arrays values against allow_pickle: bool too (no key is named so)
    np.savez_compressed(buffer, **arrays)  # type: ignore[arg-type]
    return buffer.getvalue()


def decode_arrays(blob: bytes) -> dict[str, np.ndarray]:
    """``{"poses_xyyaw_world" (N, 3), "pose_sigma_xy_m" (N,), "keyframe_indices" (K,), "gnss_inlier" (N,)}``
    and, when the single-trip stage kept them apart, ``"white_poses_xyyaw_world" (N, 3)``."""
    with np.load(io.BytesIO(blob), allow_pickle=False) as npz:
        return {name: npz[name] for name in npz.files}


def instance_json(instance: TripInstance) -> dict[str, Any]:
    return {
        "type": instance.type.value,
        "style": instance.style.value if instance.style is not None else None,
        "points_xy": np.round(instance.points_xy_world, _POINT_DECIMALS).tolist(),
        "n_observations": int(instance.n_observations),
        "first_frame": int(instance.first_frame),
        "last_frame": int(instance.last_frame),
    }


def instance_from_json(item: dict[str, Any]) -> TripInstance:
    return TripInstance(
        type=ElementType(item["type"]),
        points_xy_world=np.asarray(item["points_xy"], float).reshape(-1, 2),
        style=DividerStyle(item["style"]) if item["style"] is not None else None,
        n_observations=int(item["n_observations"]),
        first_frame=int(item["first_frame"]),
        last_frame=int(item["last_frame"]),
    )


def noise_json(noise: dict[ElementType, ElementNoise]) -> dict[str, dict[str, Any]]:
    return {
        kind.value: {
            "lateral_sigma_m": float(value.lateral_sigma_m),
            "along_sigma_m": float(value.along_sigma_m),
            "n_samples": int(value.n_samples),
        }
        for kind, value in noise.items()
    }


def noise_from_json(noise: dict[str, dict[str, Any]]) -> dict[ElementType, ElementNoise]:
    return {ElementType(kind): ElementNoise(**value) for kind, value in noise.items()}


def row_values(recon: TripReconstruction, frame: LocalFrame) -> dict[str, Any]:
    """The columns of a ``trip_reconstructions`` row (but ``trip_pk`` and ``created_at``)."""
    return {
        "algorithm_version": ALGORITHM_VERSION,
        "origin_lat": float(frame.origin_lat),
        "origin_lon": float(frame.origin_lon),
        "n_frames": recon.trip.n_frames,
        "n_keyframes": int(len(recon.keyframe_indices)),
        "n_instances": len(recon.instances),
        "arrays": encode_arrays(recon),
        "instances": [instance_json(i) for i in recon.instances],
        "noise": _plain_json(noise_json(recon.noise)),
        "diagnostics": _plain_json(recon.diagnostics),
    }


def _plain_json(value: Any) -> Any:
    """numpy scalars -> numbers, NaN -> null (PostgreSQL's json type rejects NaN)."""
    return orjson.loads(orjson.dumps(value, option=orjson.OPT_SERIALIZE_NUMPY))
