"""Parameters of lane instance topology generation and automatic validation (paper III-E).

Distances that decide "same element or not" are not constants: they come from each trip's
single-trip noise estimate (``ElementNoise.lateral_sigma_m``) combined with the alignment error
left between trips (``ALIGNMENT_SIGMA_M``, a prior: the paper's RPE RMSE, Table III), and are
bounded by road geometry (``MIN_LANE_WIDTH_M``: two distinct parallel elements of one type
are never closer than a narrow lane). The constants below are priors and physical bounds.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from csr_core.types import ElementNoise, ElementType


@dataclass(frozen=True, slots=True)
class TopologyParams:
    # --- error model --------------------------------------------------------------------------------
    # 1-sigma horizontal error left between aligned trips (paper Table III: RPE RMSE 0.087 m).
    ALIGNMENT_SIGMA_M: float = 0.10
    # lateral sigma of a type whose noise estimate is missing (single-trip prior)
    DEFAULT_LATERAL_SIGMA_M: float = 0.20

    # --- road geometry bounds -------------------------------------------------------------------------
    MIN_LANE_WIDTH_M: float = 2.5  # narrowest lane: distinct parallel elements of one type are farther
    MAX_LANE_WIDTH_M: float = 5.0  # widest lane between two dividers

    # --- association --------------------------------------------------------------------------------
    SAMPLE_SPACING_M: float = 1.0  # every instance sampled at this arclength spacing
    GATE_SIGMAS: float = 3.0  # gate = GATE_SIGMAS x combined lateral sigma of the two trips
    GATE_MAX_SHARE_OF_LANE: float = 0.3  # gate never above this share of MIN_LANE_WIDTH_M
    WINDOW_GATES: float = 2.5  # a sample is "alongside" the other instance within this many gates
    MIN_OVERLAP_M: float = 4.0  # edge needs this much mutual overlap (or half the shorter instance)
    MIN_CLOSE_SHARE: float = 0.75  # of the samples alongside, this share within the gate
    MAX_ANGLE_RAD: float = math.radians(25.0)  # samples of one element are nearly parallel
    POLYGON_GATE_M: float = 1.0  # polygons: centroid distance beyond the overlap test

    # --- implausible members (left out of fusion) ----------------------------------------------------
    # a trip instance that zig-zags: more than this turning per metre on average that smoothing
    # over ``ZIGZAG_SMOOTHING_M`` removes (roads curve, they do not oscillate: the turning of a
    # corner, a bend or a roundabout survives the smoothing, a sideways wobble with a wavelength
    # of ten-odd metres does not)
    ZIGZAG_TURN_RAD_PER_M: float = 0.05
    ZIGZAG_SMOOTHING_M: float = 4.0  # Gaussian sigma along the line; the fine scale is 1 m
    ZIGZAG_MIN_LENGTH_M: float = 30.0

    # --- fusion -------------------------------------------------------------------------------------
    BIN_M: float = 1.0  # arclength bins of the fused lateral profile
    SMOOTH_SIGMA_M: float = 2.0  # Gaussian smoothing of the profile along arclength
    TUKEY_C_SIGMAS: float = 4.685  # redescending weight: a trip farther than this is ignored
    IRLS_ITERATIONS: int = 4
    MAX_GAP_M: float = 15.0  # unsupported arclength spanned; longer gaps split the instance
    END_WINDOW_M: float = 3.0  # robust ends: member ends within this of the extreme vote
    OUTPUT_SPACING_M: float = 1.0
    MAX_FUSION_ROUNDS: int = 12  # rounds of associate -> fuse -> peel off the unsupported
    DETACH_CLOSE_SHARE: float = 0.6  # a member with less of its overlap near the fused line leaves
    # short straight elements (a trip's instance is a view of the whole or of a part of one): fused
    # on a robust straight axis; an inconsistent member is an outlier (``fusion._straight_axis``)
    WHOLE_ELEMENT_TYPES: tuple[ElementType, ...] = (ElementType.STOP_LINE,)

    # --- identity -----------------------------------------------------------------------------------
    ID_MIN_OVERLAP_SHARE: float = 0.5  # a new instance inherits an id when this share overlaps it

    # --- lane graph ---------------------------------------------------------------------------------
    CONNECT_M: float = 2.5  # lane end -> lane start within this is a successor link
    CONNECT_MAX_ANGLE_RAD: float = math.radians(45.0)
    LANE_MIN_LENGTH_M: float = 5.0  # shorter centreline pieces (fragments) are not lanes
    # lanes without a perceived centreline get one derived from their dividers and boundaries
    # (``derived_centerlines``: perception stacks with MapTR's classes report none)
    DERIVE_CENTERLINES: bool = True

    # --- validation ---------------------------------------------------------------------------------
    TILE_SIZE_M: float = 200.0  # square tiles of the world plane (the service may use its own)
    COVERAGE_RADIUS_M: float = 10.0  # a trip "passed" an instance if it has elements this close
    LOW_SUPPORT_SHARE: float = 0.34  # of the trips that passed, fewer than this saw it
    # fewer trips than this saw it: nobody checked it. Two trips associated within the noise gate
    # of each other confirm each other (measured: support 2 is wrong no more often than the map as
    # a whole; a single trip 1.5-2 x as often, hard and standard profiles)
    MIN_SUPPORT_TRIPS: int = 2
    HIGH_VARIANCE_RATIO: float = 2.0  # trip scatter / expected sigma above this
    DISAGREE_WEIGHT_SHARE: float = 0.25  # rejected (outlier) trips hold this share of the weight
    GAP_MIN_M: float = 5.0  # unsupported run inside an instance, or break to a collinear one
    # a match pair's registration residual (RMS over many points) above this many times what the
    # two trips' noise predicts (``validation.expected_pair_residual_m``): the sub-maps do not fit.
    # An RMS of tens of residuals concentrates near its sigma; twice it is far outside the noise.
    HIGH_RESIDUAL_SIGMAS: float = 2.0
    WIDTH_RUN_M: float = 5.0  # an implausible spacing must hold over this length
    # two estimates of one line differ by more than this many combined sigmas: not noise
    DUPLICATE_SIGMAS: float = 2.0
    # --- negative evidence: trips that drove alongside a line and did not see it -------------------
    # A trip "drove alongside" a line when, over at least PASS_MIN_SHARE of the line's length, its
    # path ran within PASS_LATERAL_M of it (inside the usual +-15 m lateral BEV range, away from its
    # edge where detections thin out) in a direction within PASS_MAX_ANGLE_RAD of the line's (either
    # way): it had the line in view for tens of frames. Crossing it at a junction does not count.
    PASS_LATERAL_M: float = 10.0
    PASS_MAX_ANGLE_RAD: float = math.radians(30.0)
    PASS_MIN_SHARE: float = 0.5
    # a line that at least this many trips drove alongside without seeing it, and that fewer than
    # LOW_SUPPORT_SHARE of all the trips that had it in view saw, is held back from the map
    # (``TopologyResult.suppressed``) until more trips confirm it (0: never held back)
    SUPPRESS_MIN_PASSING: int = 3
    # ... and the end stretch of a line that at most one trip covered, by the same test (unseen_tails)
    TRIM_UNSEEN_TAILS: bool = True

    def trip_sigma_m(self, noise: ElementNoise | None) -> float:
        """Lateral 1-sigma of one trip's instance in the world: its perception noise plus the
        alignment error between trips."""
        lat = noise.lateral_sigma_m if noise is not None else self.DEFAULT_LATERAL_SIGMA_M
        return math.hypot(lat, self.ALIGNMENT_SIGMA_M)

    def gate_m(self, sigma_a_m: float, sigma_b_m: float) -> float:
        """Association gate between two trips' instances (metres)."""
        return min(
            self.GATE_SIGMAS * math.hypot(sigma_a_m, sigma_b_m),
            self.GATE_MAX_SHARE_OF_LANE * self.MIN_LANE_WIDTH_M,
        )


DEFAULT = TopologyParams()
