"""Parameters of single-trip reconstruction (paper section III-C), every threshold named with units.

Where a value can be read from the trip itself it is: the receiver's own ``std_m`` before the
status table, the BEV range from ``sensor_setup`` (else from the detections), track support
from the frame spacing. The constants below are priors and physical bounds, not fits to a seed.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from csr_core.types import ElementType


@dataclass(frozen=True, slots=True)
class SingleTripParams:
    # --- GNSS factors (Eq. 2) ------------------------------------------------------------------
    # 1-sigma horizontal error per status code (GnssStatus order: rtk_fixed, rtk_float, dgps,
    # single, none), used only when the receiver gives no std_m. Typical receiver figures.
    GNSS_SIGMA_BY_STATUS_M: tuple[float, ...] = (0.05, 0.5, 1.0, 3.0, math.inf)
    # Lower bound of any GNSS sigma: receivers under-report; also keeps the graph well scaled.
    GNSS_SIGMA_FLOOR_M: float = 0.05
    # GNSS errors (multipath, atmosphere) are correlated over seconds; fixes within this time
    # count as one independent fix in the graph (0: every fix independent).
    GNSS_CORRELATION_S: float = 30.0
    # A last solve with the GNSS error as a Gauss-Markov bias state per node (gnss_bias.py): each
    # fix then weighs only its white part, and the trip keeps its shape where the bias wanders.
    # The white solve before this one is kept with the trip (``TripReconstruction.white_poses_xyyaw_world``):
    # the alignment's e^sm chain takes a trip's relative poses from it (with the bias state's, the
    # alignment lost on the dense fleets and in the per-tile service: docs/single-trip.md,
    # docs/alignment.md). TAU is the bias's correlation time: longer than
    # the tens of seconds GNSS_CORRELATION_S assumes, shorter than the real u-blox log's (its
    # offset stays within 0.1 m over a minute, docs/gnss-model.md); 30-300 s all beat the white
    # model on every world. The white sigma is measured per trip and status.
    GNSS_BIAS_STATE: bool = True
    GNSS_BIAS_TAU_S: float = 120.0
    GNSS_WHITE_SIGMA_MIN_M: float = 0.01
    # GNSS latency (fix stamped t = position at t - L), estimated per trip; windows remove the bias
    GNSS_LATENCY_ESTIMATE: bool = True
    GNSS_LATENCY_WINDOW_S: float = 20.0
    GNSS_LATENCY_MAX_S: float = 0.5
    GNSS_LATENCY_ROBUST_Z: float = 3.0  # kept when > 3 sigma, windows as clusters (0: chi-square test alone)
    # Width of the robust kernel, in sigmas. Stage 1 is Huber (convex: converges from the rigid
    # initial fit), stage 2 Cauchy (rejects GNSS jumps), warm-started from stage 1.
    GNSS_HUBER_K_SIGMAS: float = 1.5
    GNSS_CAUCHY_C_SIGMAS: float = 2.0
    # GNSS course is the velocity direction, equal to the yaw only when moving.
    GNSS_HEADING_SIGMA_RAD: float = math.radians(3.0)
    GNSS_HEADING_MIN_SPEED_MPS: float = 3.0
    GNSS_HEADING_CAUCHY_C_SIGMAS: float = 2.0
    # Every fix's course, its sigma measured on the trip (gnss_course.py). Off: one
    # course per node at GNSS_HEADING_SIGMA_RAD (also the fallback with too few courses). On once
    # courses came into the plane through its meridian convergence: the
    # per-tile service had lost with it only for that (docs/single-trip.md).
    GNSS_HEADING_PER_FIX: bool = True
    COURSE_DECORRELATION_S: float = 1.0  # course changes over this long measure the noise
    GNSS_COURSE_SIGMA_FLOOR_RAD: float = math.radians(0.05)
    # Hard rejection of GNSS jumps: residual norm over (sigma x data scale) above this (Rayleigh
    # tail 0.2 % at 3.5). The scale is the trip's median normalised residual, at least SCALE_MIN.
    GNSS_OUTLIER_SIGMAS: float = 3.5
    GNSS_SCALE_MIN: float = 0.5
    GNSS_REJECTION_ROUNDS: int = 3
    GNSS_MIN_INLIER_SHARE: float = 0.3  # never reject more than 70 % of a trip's fixes

    # --- odometry factors (Eq. 2): sigma grows with the distance of the increment ------------------
    # (after the per-trip calibration of scale and yaw-rate bias below)
    ODOM_SIGMA_XY_PER_M: float = 0.005  # metres per metre travelled (0.5 %)
    ODOM_SIGMA_XY_FLOOR_M: float = 0.002  # per increment (standing still)
    ODOM_SIGMA_YAW_PER_M: float = math.radians(0.01)  # radians per metre travelled
    ODOM_SIGMA_YAW_PER_S: float = math.radians(
        0.01
    )  # gyro drift (random walk), beside the bias left after calibration
    ODOM_SIGMA_YAW_FLOOR_RAD: float = math.radians(0.002)  # per increment

    # per-trip odometry calibration against GNSS (scale error, constant yaw-rate bias)
    CAL_ENABLED: bool = True
    CAL_WINDOW_M: float = 100.0  # GNSS/odometry displacement pairs this far apart
    CAL_MIN_DURATION_S: float = 60.0  # yaw-rate bias only from trips at least this long
    CAL_MAX_SCALE_ERROR: float = 0.05
    # physical prior of an automotive gyro's yaw-rate bias after its own start-up calibration
    # (a few hundredths of a degree per second); the chord estimate is combined with it
    CAL_YAW_RATE_BIAS_PRIOR_RAD_S: float = math.radians(0.05)
    CAL_MIN_INDEPENDENT_CHORDS: int = 4  # non-overlapping GNSS/odometry chords for an estimate

    # --- integrity: the poses tested against the trip's own GNSS (integrity.py) -----------------
    INTEGRITY_CHECK: bool = True
    INTEGRITY_WINDOW_S: float = 20.0  # shorter than the GNSS bias's correlation time
    INTEGRITY_FALSE_ALARM: float = 1e-3  # per trip, shared by its windows (Bonferroni)
    INTEGRITY_MEDIAN_FACTOR: float = 1.5  # the trip's median distance to its fixes over the error model's
    INTEGRITY_MAX_REJECTED_SHARE: float = 0.25  # of the trip's fixes rejected by the smoother
    # aligned poses: their median distance to the fixes is the GNSS bias itself; 3 x the
    # Rayleigh median is 3.5 sigma, a chi-square(2) tail of 2e-3, like one window's limit
    INTEGRITY_ALIGNED_MEDIAN_FACTOR: float = 3.0
    INTEGRITY_REPAIR_YAW_FACTOR: float = 30.0  # repair: the odometry yaw drift sigma times this
    INTEGRITY_REPAIR_XY_FACTOR: float = 4.0  # repair: the odometry distance sigma times this
    INTEGRITY_ANCHOR_YAW_FACTOR: float = 300.0  # fallback: odometry sigmas times this (GNSS-anchored)

    # graph nodes (frames in between follow the odometry): keeps the cost per km fixed
    POSE_NODE_SPACING_M: float = 5.0
    POSE_NODE_PERIOD_S: float = 1.0

    LM_MAX_ITERATIONS: int = 50
    LM_RELATIVE_ERROR_TOL: float = 1e-4

    # --- keyframes ---------------------------------------------------------------------------------
    KEYFRAME_DISTANCE_M: float = 5.0
    KEYFRAME_PERIOD_S: float = 5.0  # a keyframe at least this often, even standing still

    # --- tracking (Qiao et al.) ----------------------------------------------------------------------
    TRACK_STEP_M: float = (
        5.0  # frames are tracked once the vehicle moved this far: 9 per pass of the 45 m BEV length
    )
    TRACK_STEP_S: float = 1.0  # ... or this long
    TRACK_RESAMPLE_POINTS: int = 6  # points per detection in the association cost
    TRACK_DISTANCE_CAP_M: float = 3.0  # truncation of point distances in the Chamfer cost
    TRACK_GATE_M: float = 0.9  # Chamfer gate at zero pose uncertainty; grows with it
    TRACK_GATE_SIGMAS: float = 3.0  # gate in sigmas of the combined lateral noise
    TRACK_LATERAL_WEIGHT: float = 0.3  # weight of the lateral-order term in the assignment cost
    TRACK_MAX_EXTRAPOLATION_M: float = 12.0  # a detection may extend a track by at most this
    TRACK_COARSE_MARGIN_M: float = 1.0  # pre-test of pairs on middle points: gate + this
    TRACK_MAX_ANGLE_RAD: float = math.radians(20.0)  # pieces of one element are nearly parallel
    TRACK_MAX_SKIP_FRAMES: int = 2  # links reach this many tracked frames ahead (missed detections)
    TRACK_MERGE_GATE_M: float = 0.6  # an unassigned piece collinear with a matched track joins it
    # kerbs and centrelines: within a frame, a piece joins another only end to end, one per end (a
    # lane ends where its connectors start: tracking.one_continuation_per_end). Left off: on, the
    # trip-level completeness rises and duplicates go, but so many correct duplicate samples go with
    # them that Karlsruhe s3's rigid correctness share falls under 0.97 (docs/single-trip.md)
    TRACK_MERGE_ONE_PER_END: bool = False
    # dashed-divider tracks re-cut into the lines their dashes form: a track across the path that no
    # line or circle carries split into its dashes, and dashes and tracks chained end to end where
    # one circle carries them (a junction's guide line tracked dash by dash: dash_chaining.py)
    DASH_CHAINING: bool = True

    # --- ghosts and false positives -----------------------------------------------------------------
    TRACK_MIN_FRAMES: int = 4  # tracked frames supporting an instance
    # a track holding the trip's first or last tracked frame was cut short by the trip, not by its
    # detector: this many frames hold it if it was seen in every tracked frame that had it in range
    TRACK_MIN_FRAMES_AT_TRIP_END: int = 2
    TRACK_MIN_VISIBILITY_RATIO: float = 0.35  # seen / in-range tracked frames
    BEV_RANGE_MARGIN_M: float = 2.0  # an instance point counts as in range this far inside the BEV box
    # an instance is kept within this of the trip's path at most (and within its BEV's lateral reach):
    # the corridor the map is defined and scored in (contract section 6: truth within 15 m of the
    # trips' frames). A sensor that reaches farther sees the rest at its far edge, where it is
    # noisiest, and the trips that drive there see it better
    INSTANCE_MAX_LATERAL_M: float = 15.0
    INSTANCE_MAX_SIGMA_RATIO: float = 2.0  # own lateral residual sigma / its type's, above: a mixture
    # ... and above this (metres): two painted elements side by side are at least a line's width
    # (~0.15 m) apart, so a splice mixing them spreads its residuals by at least half of that. Without
    # it, a perception with millimetre noise made every dashed divider a "mixture" (residuals of
    # 1 cm from the dash chaining against a type sigma of 2 mm) and dropped it
    INSTANCE_MIXTURE_MIN_SIGMA_M: float = 0.075
    INSTANCE_MIN_LENGTH_M: dict[ElementType, float] | None = None  # None: defaults below

    # --- paint breaks (paint_breaks.py) ---------------------------------------------------------------
    # a lane divider's stretch with none of its own observations within GATE (the splice bridged
    # it) that comes within REACH of a stop line or crosswalk of the trip is a break in the paint:
    # the instance is cut there. Both one splice bin (SPLICE_BIN_M, the spacing the observations
    # are densified to). A REACH of 2 m also cut dash gaps that the truth holds (Karlsruhe s3, true
    # poses: divider completeness 0.863 -> 0.855 for correctness 0.979 -> 0.981; docs/single-trip.md)
    PAINT_BREAKS: bool = True
    PAINT_BREAK_GATE_M: float = 1.0
    PAINT_BREAK_REACH_M: float = 1.0
    # road boundaries and centrelines are continuous: a stretch of one with none of its own
    # observations within PAINT_BREAK_GATE_M is not a dash gap but a bridge the splice made (round
    # a U-turn the trip made at a dead end), or an end carried past what was seen; the instance
    # is cut there, whatever lies beside it
    CONTINUOUS_UNSEEN_CUT: bool = True
    # "seen" for that cut: an observation within SIGMAS x the type's lateral noise in the trip
    # (its residuals before the cut) plus half of STEP, the spacing the observations are densified
    # to for it; at most PAINT_BREAK_GATE_M. 0: PAINT_BREAK_GATE_M for every trip.
    # A splice standing 0.6-0.8 m off its own observations (fragments of junction centrelines,
    # Karlsruhe) is inside 1 m but far outside the noise (docs/single-trip.md)
    UNSEEN_CUT_SIGMAS: float = 3.0
    UNSEEN_CUT_STEP_M: float = 0.25

    # --- splicing ------------------------------------------------------------------------------------
    # a polygon never seen whole: its rectangle's axes from its observed sides, not from the
    # principal axes of the clipped outlines (splicing._robust_rectangle)
    POLYGON_EDGE_AXES: bool = True
    SPLICE_BIN_M: float = 1.0  # arclength bins of the robust lateral profile
    SPLICE_SMOOTH_SIGMA_M: float = 2.0  # Gaussian smoothing of the lateral profile along arclength
    SPLICE_OUTLIER_SIGMAS: float = 3.0
    SPLICE_MAX_GAP_M: float = 15.0  # unsupported arclength spanned (dash gaps); longer gaps split
    SPLICE_CLUSTER_D_M: float = 0.5  # lateral cell of the element clustering inside a track
    SPLICE_MIXTURE_SIGMA_M: float = 0.35  # lateral spread above which a cluster is split into modes
    SPLICE_MODE_GAP_M: float = 1.0  # lateral gap between modes of one arclength bin
    SPLICE_MODE_GATE_M: float = 0.6  # a mode continues the nearest chain within this (per step)
    SPLICE_GUIDE_EXTENSION_M: float = 40.0  # the path guide prolonged at both ends (BEV reach)
    SPLICE_ALONG_GUIDE_MIN: float = 0.9  # |d arclength on the path| / chord: element runs along the path
    SPLICE_ACROSS_WINDOW_M: float = (
        2.5  # a splice is cut where, within this either side, its observations cross it
    )
    # a splice no part of which runs along its observations (it joined elements that meet at an
    # angle: a kerb's two legs round a traffic island) is regrouped like a mixture and each group
    # spliced on its own shape, instead of dropped (docs/single-trip.md)
    SPLICE_REGROUP_ACROSS: bool = True
    SPLICE_STRAIGHT_BELOW_M: float = 10.0  # shorter elements (stop lines) spliced on their principal axis
    SPLICE_BACKBONE_SMOOTH_M: float = 3.0  # Gaussian smoothing of a backbone grown from observations
    SPLICE_OUTPUT_SPACING_M: float = 1.0

    # --- noise prior (used where a type has too few residuals) -----------------------------------------
    NOISE_PRIOR_LATERAL_M: float = 0.2
    NOISE_PRIOR_ALONG_M: float = 0.5
    NOISE_MIN_SAMPLES: int = 30
    NOISE_END_WINDOW_M: float = 3.0  # observed ends this close to an instance end give along residuals

    def min_length_m(self, element_type: ElementType) -> float:
        table = self.INSTANCE_MIN_LENGTH_M or {
            ElementType.LANE_DIVIDER: 3.0,
            ElementType.ROAD_BOUNDARY: 3.0,
            ElementType.CENTERLINE: 3.0,
            ElementType.STOP_LINE: 1.0,
            ElementType.CROSSWALK: 0.0,
            ElementType.ROAD_MARKING: 0.0,
        }
        return table.get(element_type, 0.0)


DEFAULT = SingleTripParams()
