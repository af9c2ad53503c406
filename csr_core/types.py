"""Domain types shared by every stage, and the frame conventions, written once.

Frames and conventions
----------------------
- ``world``: the local transverse-Mercator plane of a region (see ``csr_core.geo``):
  x east, y north, metres.
- ``vehicle``: x forward, y left, metres; yaw counter-clockwise from world x (radians).
- ``odom``: the trip's own dead-reckoning frame, as uploaded; only differences matter.
- A pose is ``(x, y, yaw)``; ``a_T_b`` maps coordinates in frame b into frame a, so
  ``world_T_vehicle`` applied to ``points_xy_vehicle`` gives ``points_xy_world``; poses
  compose left to right: ``a_T_c = a_T_b @ b_T_c`` (see ``csr_core.se2``).
- GNSS ``heading_deg`` is clockwise from north; ``yaw_rad = pi/2 - radians(heading_deg)``.

Arrays are named by layout: ``poses_xyyaw (N, 3)``, ``points_xy (M, 2)``, ``timestamps_s (N,)``.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from enum import Enum, IntEnum

import numpy as np


class ElementType(str, Enum):
    LANE_DIVIDER = "lane_divider"
    ROAD_BOUNDARY = "road_boundary"
    CENTERLINE = "centerline"
    STOP_LINE = "stop_line"
    CROSSWALK = "crosswalk"
    ROAD_MARKING = "road_marking"

    @property
    def is_polygon(self) -> bool:
        return self in (ElementType.CROSSWALK, ElementType.ROAD_MARKING)


LINE_TYPES = (
    ElementType.LANE_DIVIDER,
    ElementType.ROAD_BOUNDARY,
    ElementType.CENTERLINE,
    ElementType.STOP_LINE,
)
POLYGON_TYPES = (ElementType.CROSSWALK, ElementType.ROAD_MARKING)


class DividerStyle(str, Enum):
    SOLID = "solid"
    DASHED = "dashed"
    DOUBLE = "double"
    UNKNOWN = "unknown"


class GnssStatus(IntEnum):
    """Receiver fix quality, best first. The integer code is what arrays store."""

    RTK_FIXED = 0
    RTK_FLOAT = 1
    DGPS = 2
    SINGLE = 3
    NONE = 4

    @classmethod
    def from_name(cls, name: str) -> GnssStatus:
        return cls[name.upper()]

    @property
    def wire_name(self) -> str:
        return self.name.lower()


def _check_shape(name: str, array: np.ndarray, shape: tuple[int | None, ...]) -> None:
    if array.ndim != len(shape) or any(
        s is not None and s != a for s, a in zip(shape, array.shape, strict=True)
    ):
        raise ValueError(f"{name} must have shape {shape}, got {array.shape}")


@dataclass(frozen=True, slots=True)
class PerceivedElement:
    """One road element seen in one frame, in that frame's vehicle frame (metres)."""

    type: ElementType
    points_xy_vehicle: np.ndarray  # (M, 2)
    style: DividerStyle | None = None
    score: float = float("nan")
    track_id: int | None = None

    def __post_init__(self) -> None:
        _check_shape("points_xy_vehicle", self.points_xy_vehicle, (None, 2))


@dataclass(frozen=True, slots=True)
class Trip:
    """A decoded trip upload (contract section 1), arrays in upload order.

    ``gnss_lonlat_deg`` rows with status NONE carry no fix (their values are meaningless).
    ``gnss_std_m`` and ``gnss_heading_deg`` are NaN where the receiver gave none.
    """

    vehicle_id: str
    trip_id: str
    started_at: str
    timestamps_s: np.ndarray  # (N,)
    gnss_lonlat_deg: np.ndarray  # (N, 2) lon, lat
    gnss_status: np.ndarray  # (N,) uint8 GnssStatus codes
    gnss_std_m: np.ndarray  # (N,)
    gnss_heading_deg: np.ndarray  # (N,)
    odom_xyyaw: np.ndarray  # (N, 3) metres, radians, odometry frame
    elements: tuple[tuple[PerceivedElement, ...], ...]  # per frame
    sensor_setup: dict = field(default_factory=dict)

    def __post_init__(self) -> None:
        n = self.timestamps_s.shape[0]
        _check_shape("timestamps_s", self.timestamps_s, (n,))
        _check_shape("gnss_lonlat_deg", self.gnss_lonlat_deg, (n, 2))
        _check_shape("gnss_status", self.gnss_status, (n,))
        _check_shape("gnss_std_m", self.gnss_std_m, (n,))
        _check_shape("gnss_heading_deg", self.gnss_heading_deg, (n,))
        _check_shape("odom_xyyaw", self.odom_xyyaw, (n, 3))
        if len(self.elements) != n:
            raise ValueError(f"elements must have one entry per frame ({n}), got {len(self.elements)}")

    @property
    def key(self) -> str:
        """``<vehicle_id>__<trip_id>``: the file stem used by scenario folders and outputs."""
        return f"{self.vehicle_id}__{self.trip_id}"

    @property
    def n_frames(self) -> int:
        return int(self.timestamps_s.shape[0])

    @property
    def held_fix(self) -> np.ndarray:
        """(N,) frames whose fix repeats the previous frame's bit for bit: a receiver slower
        than the frames, its last epoch copied into the frames between. Not a new measurement
        (as a new one it would be a position up to an epoch late, a staircase along the road)."""
        fix = self.gnss_status != GnssStatus.NONE
        same = np.all(self.gnss_lonlat_deg[1:] == self.gnss_lonlat_deg[:-1], axis=1)
        return np.r_[False, same & fix[1:] & fix[:-1]]

    @property
    def has_fix(self) -> np.ndarray:
        """(N,) frames with a fix of their own: status not ``none`` and not a held repeat."""
        return (self.gnss_status != GnssStatus.NONE) & ~self.held_fix

    @property
    def fix_status(self) -> np.ndarray:
        """``gnss_status`` with held repeats (:attr:`held_fix`) as ``none``: what the stages
        that weigh fixes read."""
        return np.where(self.held_fix, np.uint8(GnssStatus.NONE), self.gnss_status).astype(np.uint8)


# --- stage outputs ----------------------------------------------------------------------------


@dataclass(frozen=True, slots=True)
class ElementNoise:
    """Noise estimate of one element type from single-trip residuals (sets Eq. 3, 5, 6 thresholds)."""

    lateral_sigma_m: float
    along_sigma_m: float
    n_samples: int = 0


@dataclass(frozen=True, slots=True)
class TripInstance:
    """A trip-level road element: one track of per-frame detections spliced and smoothed,
    in the world frame of the trip's smoothed poses."""

    type: ElementType
    points_xy_world: np.ndarray  # (M, 2); polygons: outline, first point not repeated
    style: DividerStyle | None = None
    n_observations: int = 0
    first_frame: int = 0
    last_frame: int = 0

    def __post_init__(self) -> None:
        _check_shape("points_xy_world", self.points_xy_world, (None, 2))


@dataclass(frozen=True, slots=True)
class TripReconstruction:
    """Result of single-trip reconstruction (paper section III-C), the input of alignment.

    ``poses_xyyaw_world`` are the smoothed world_T_vehicle poses of every uploaded frame (Eq. 2);
    ``pose_sigma_xy_m`` their marginal horizontal standard deviation. ``white_poses_xyyaw_world``
    (optional, with the single-trip GNSS bias state): the white-noise solve before the bias state,
    from which the alignment's e^sm chain takes the trip's relative poses
    (``AlignmentParams.submap_chain_from_white_solve``).
    """

    trip: Trip
    poses_xyyaw_world: np.ndarray  # (N, 3)
    pose_sigma_xy_m: np.ndarray  # (N,)
    keyframe_indices: np.ndarray  # (K,) int, ascending
    instances: tuple[TripInstance, ...]
    noise: dict[ElementType, ElementNoise]
    # optional: per-frame GNSS fix kept by the robust smoother (N,) bool, or None
    gnss_inlier: np.ndarray | None = None
    # optional: per-trip estimates and timings (odometry scale, yaw-rate bias, GNSS latency, ...)
    diagnostics: dict = field(default_factory=dict)
    white_poses_xyyaw_world: np.ndarray | None = None  # (N, 3)

    def __post_init__(self) -> None:
        n = self.trip.n_frames
        _check_shape("poses_xyyaw_world", self.poses_xyyaw_world, (n, 3))
        _check_shape("pose_sigma_xy_m", self.pose_sigma_xy_m, (n,))
        if self.white_poses_xyyaw_world is not None:
            _check_shape("white_poses_xyyaw_world", self.white_poses_xyyaw_world, (n, 3))


@dataclass(frozen=True, slots=True)
class MapFeature:
    """One element of the reconstructed road structure, world frame (like ``GET /v1/map``)."""

    type: ElementType
    points_xy_world: np.ndarray  # (M, 2); polygons: outline, first point not repeated
    style: DividerStyle | None = None
    feature_id: str = ""
    properties: dict = field(default_factory=dict)


@dataclass(frozen=True, slots=True)
class Reconstruction:
    """What the whole pipeline returns for a batch of trips (``csr reconstruct``).

    ``poses_xyyaw_world`` maps ``trip.key`` to the final world_T_vehicle pose of every uploaded
    frame; a trip that failed alignment is absent there and present in ``failed`` with a reason.
    ``held_back_features`` are lines the topology kept out of ``map_features`` (trips drove
    alongside them without seeing them: ghosts, mis-spliced lines) for a human to look at.
    """

    origin_lat: float
    origin_lon: float
    poses_xyyaw_world: dict[str, np.ndarray]
    map_features: tuple[MapFeature, ...]
    failed: dict[str, str] = field(default_factory=dict)
    diagnostics: dict = field(default_factory=dict)
    held_back_features: tuple[MapFeature, ...] = ()
    # trips whose poses are present but not to be trusted: trip key -> reason (the integrity
    # test against the trip's own GNSS failed even after the repair; ``single_trip.integrity``)
    degraded: dict[str, str] = field(default_factory=dict)
