"""Accuracy metrics, exactly as contract section 6 defines them (so every figure compares).

Everything is in one local plane (metres): the caller projects truth and estimate with the
scenario's :class:`csr_core.geo.LocalFrame` (tmerc centred on the scenario origin).

- Global alignment: one rigid SE(2) ``truth_T_est`` (2-D Kabsch/Umeyama without scale, least
  squares over all frames of all trips) applied to poses and map for the *aligned* figures.
- ATE: RMSE and mean of the horizontal position error over all frames of all trips.
- RPE: each frame ``i`` paired with the first later frame ``j`` of the same trip whose *true*
  path length from ``i`` is >= 10 m; error ``|(est_j - est_i) - (true_j - true_i)|`` in the map
  plane; RMSE and mean over all pairs of all trips. Frames with no such ``j`` have no pair.
- Coverage: ``trips_with_poses / trips``; failed trips are left out of ATE and RPE.
- Map, per element type: samples every 0.5 m along lines and along polygon outlines; truth
  samples kept only within 15 m of some true trajectory frame. Distances go to the other side's
  polylines / outlines: exact point-to-segment distances, vectorized (candidate pairs from a
  cKDTree over the other side's segments cut into short pieces; see
  :func:`distances_to_segments`). Capped at 1 m; an empty side counts as the cap.
  CD = 0.5 (mean_pred min(d, 1) + mean_truth min(d, 1)); completeness = share of truth samples
  within 0.5 m of the prediction, correctness = share of predicted samples within 0.5 m of truth;
  mCD = mean CD over lane_divider, centerline, road_boundary.

ATE and RPE are cross-checked against evo (:func:`evo_trajectory_errors`, used by the tests).
Speed: a 20 trips x 2 km scenario (59k frames, 15k predicted features) evaluates in ~10 s on
the shared, loaded 2-core development machine (raw and aligned, all types).

Choices the contract leaves open (documented here, used everywhere):

- "Truth is kept only within 15 m" applies to the truth *geometry*: the prediction's distance
  to truth is to the truth polylines clipped to the corridor (the chain of kept samples and
  original vertices), so predicted elements far outside the evaluated corridor count as wrong.
- A type with no truth in the corridor and no prediction has CD = NaN (not scored, shown as
  "-"); with prediction but no truth, CD = 1 m (both sides at the cap).
"""

from __future__ import annotations

import logging
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field

import numpy as np
from scipy.spatial import cKDTree

from csr_core.types import ElementType, MapFeature

log = logging.getLogger(__name__)

SAMPLE_STEP_M = 0.5
TRUTH_CORRIDOR_M = 15.0
CD_CAP_M = 1.0
MATCH_THRESHOLD_M = 0.5
RPE_DELTA_M = 10.0
MCD_TYPES = (ElementType.LANE_DIVIDER, ElementType.CENTERLINE, ElementType.ROAD_BOUNDARY)
TABLE_TYPES = MCD_TYPES + (ElementType.STOP_LINE, ElementType.CROSSWALK)


# --- statistics ---------------------------------------------------------------------------------


@dataclass(frozen=True, slots=True)
class ErrorStats:
    """RMSE and mean of a set of non-negative errors (metres); NaN when ``n == 0``."""

    rmse: float
    mean: float
    n: int

    @classmethod
    def of(cls, errors_m: np.ndarray) -> ErrorStats:
        errors_m = np.asarray(errors_m, float)
        if errors_m.size == 0:
            return cls(float("nan"), float("nan"), 0)
        return cls(float(np.sqrt(np.mean(errors_m**2))), float(np.mean(errors_m)), int(errors_m.size))


# --- alignment ----------------------------------------------------------------------------------


def umeyama_se2(src_xy: np.ndarray, dst_xy: np.ndarray) -> np.ndarray:
    """Least-squares rigid SE(2) ``dst_T_src`` (no scale) with ``dst ~ R src + t``.

    ``src_xy, dst_xy (N, 2)`` paired rows. Returns ``(3,)`` ``(tx, ty, yaw)``. Raises
    ``ValueError`` for fewer than 2 pairs or all-identical source points (rotation undefined).
    """
    src_xy = np.asarray(src_xy, float).reshape(-1, 2)
    dst_xy = np.asarray(dst_xy, float).reshape(-1, 2)
    if src_xy.shape != dst_xy.shape:
        raise ValueError(f"shapes differ: {src_xy.shape} vs {dst_xy.shape}")
    if len(src_xy) < 2:
        raise ValueError("umeyama_se2 needs at least 2 point pairs")
    mu_s, mu_d = src_xy.mean(axis=0), dst_xy.mean(axis=0)
    a, b = src_xy - mu_s, dst_xy - mu_d
    if np.allclose(a, 0.0):
        raise ValueError("umeyama_se2: source points are all identical, rotation undefined")
    # For 2-D the optimal rotation angle has a closed form: atan2(sum cross, sum dot).
    yaw = np.arctan2(
        np.sum(a[:, 0] * b[:, 1] - a[:, 1] * b[:, 0]), np.sum(a[:, 0] * b[:, 0] + a[:, 1] * b[:, 1])
    )
    c, s = np.cos(yaw), np.sin(yaw)
    t = mu_d - np.array([c * mu_s[0] - s * mu_s[1], s * mu_s[0] + c * mu_s[1]])
    return np.array([t[0], t[1], yaw])


def apply_se2(a_T_b: np.ndarray, points_xy_b: np.ndarray) -> np.ndarray:
    """``(3,)`` pose applied to ``(N, 2)`` points."""
    c, s = np.cos(a_T_b[2]), np.sin(a_T_b[2])
    p = np.asarray(points_xy_b, float).reshape(-1, 2)
    return np.column_stack([c * p[:, 0] - s * p[:, 1] + a_T_b[0], s * p[:, 0] + c * p[:, 1] + a_T_b[1]])


# --- trajectory errors --------------------------------------------------------------------------


def position_errors(est_xy: np.ndarray, true_xy: np.ndarray) -> np.ndarray:
    """``(N,)`` horizontal position errors (the ATE terms)."""
    return np.linalg.norm(np.asarray(est_xy, float) - np.asarray(true_xy, float), axis=1)


def rpe_pair_indices(true_xy: np.ndarray, delta_m: float = RPE_DELTA_M) -> tuple[np.ndarray, np.ndarray]:
    """Contract RPE pairs of one trip: for each frame ``i`` the first later ``j`` whose true path
    length ``s_j - s_i >= delta_m``. Returns ``(i, j)`` int arrays (frames without one dropped).

    Differs from evo's ``filter_pairs_by_path(all_pairs=True)``, which takes the ``j`` whose path
    length is *closest* to delta (possibly below it) and drops pairs off by more than ``tol``.
    """
    true_xy = np.asarray(true_xy, float)
    if len(true_xy) < 2:
        return np.zeros(0, int), np.zeros(0, int)
    s = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(true_xy, axis=0), axis=1))])
    j = np.searchsorted(s, s + delta_m - 1e-9, side="left")
    i = np.arange(len(s))
    ok = j < len(s)
    return i[ok], j[ok]


def rpe_errors(est_xy: np.ndarray, true_xy: np.ndarray, delta_m: float = RPE_DELTA_M) -> np.ndarray:
    """``(P,)`` contract RPE errors of one trip (map-plane displacement differences)."""
    i, j = rpe_pair_indices(true_xy, delta_m)
    d_est = est_xy[j] - est_xy[i]
    d_true = true_xy[j] - true_xy[i]
    return np.linalg.norm(d_est - d_true, axis=1)


@dataclass(frozen=True, slots=True)
class TrajectoryScores:
    ate: ErrorStats
    rpe: ErrorStats


def trajectory_scores(
    est_xy_by_key: Mapping[str, np.ndarray], true_xy_by_key: Mapping[str, np.ndarray], keys: Sequence[str]
) -> TrajectoryScores:
    if not keys:
        return TrajectoryScores(ErrorStats.of(np.zeros(0)), ErrorStats.of(np.zeros(0)))
    ate = np.concatenate([position_errors(est_xy_by_key[k], true_xy_by_key[k]) for k in keys])
    rpe = np.concatenate([rpe_errors(est_xy_by_key[k], true_xy_by_key[k]) for k in keys])
    return TrajectoryScores(ErrorStats.of(ate), ErrorStats.of(rpe))


# --- map geometry -------------------------------------------------------------------------------


def _as_chains(features: Sequence[MapFeature]) -> list[np.ndarray]:
    """Vertex chains: polylines as they are, polygon outlines closed (first point repeated)."""
    chains = []
    for f in features:
        p = np.asarray(f.points_xy_world, float).reshape(-1, 2)
        if len(p) == 0:
            continue
        if f.type.is_polygon and len(p) > 2:
            p = np.vstack([p, p[:1]])
        chains.append(p)
    return chains


@dataclass(frozen=True, slots=True)
class _FlatChains:
    """All chains in one array: ``vertices (V, 2)``, ``chain (V,)`` ids, and a global arc length
    ``s (V,)`` that grows along each chain and jumps by 1 m between chains (so interpolating by
    ``s`` never crosses from one chain into the next)."""

    vertices: np.ndarray
    chain: np.ndarray
    s: np.ndarray
    start_s: np.ndarray  # (C,)
    length_m: np.ndarray  # (C,)
    closed: np.ndarray  # (C,) bool

    def at(self, s_query: np.ndarray) -> np.ndarray:
        return np.column_stack(
            [np.interp(s_query, self.s, self.vertices[:, 0]), np.interp(s_query, self.s, self.vertices[:, 1])]
        )


def _flatten(features: Sequence[MapFeature]) -> _FlatChains | None:
    feats = [f for f in features if len(f.points_xy_world)]
    chains = _as_chains(feats)
    if not chains:
        return None
    sizes = np.array([len(c) for c in chains])
    vertices = np.concatenate(chains)
    chain = np.repeat(np.arange(len(chains)), sizes)
    steps = np.linalg.norm(np.diff(vertices, axis=0), axis=1)
    steps[chain[1:] != chain[:-1]] = 1.0  # gap between chains
    s = np.concatenate([[0.0], np.cumsum(steps)])
    first = np.cumsum(sizes) - sizes
    last = first + sizes - 1
    closed = np.array([f.type.is_polygon and len(f.points_xy_world) > 2 for f in feats])
    return _FlatChains(vertices, chain, s, s[first], s[last] - s[first], closed)


def _sample_positions(flat: _FlatChains, step_m: float) -> tuple[np.ndarray, np.ndarray]:
    """Global arc positions of the samples every ``step_m`` (open lines: both ends; closed
    outlines: the closing point not repeated) and their chain ids."""
    length = flat.length_m
    n_regular = np.where(length > 0, np.ceil(length / step_m - 1e-12), 1).astype(int)
    n_regular = np.maximum(n_regular, 1)
    add_end = ~flat.closed & (length - (n_regular - 1) * step_m > 1e-9)
    counts = n_regular + add_end
    chain = np.repeat(np.arange(len(length)), counts)
    k = np.arange(counts.sum()) - np.repeat(np.cumsum(counts) - counts, counts)
    d = np.minimum(k * step_m, length[chain])  # the extra end sample lands on the length
    return flat.start_s[chain] + d, chain


def sample_features(features: Sequence[MapFeature], step_m: float = SAMPLE_STEP_M) -> np.ndarray:
    """``(S, 2)`` samples every ``step_m`` along each line (both ends included) and along each
    polygon outline (closing point not repeated)."""
    flat = _flatten(features)
    if flat is None:
        return np.zeros((0, 2))
    return flat.at(_sample_positions(flat, step_m)[0])


def _segments(chains: Sequence[np.ndarray]) -> np.ndarray:
    """``(K, 2, 2)`` segments of vertex chains; single points become zero-length segments."""
    segs = []
    for c in chains:
        if len(c) == 1:
            segs.append(np.stack([c, c], axis=1))
        else:
            segs.append(np.stack([c[:-1], c[1:]], axis=1))
    return np.concatenate(segs) if segs else np.zeros((0, 2, 2))


def _split_segments(segments: np.ndarray, max_len_m: float) -> np.ndarray:
    """Split ``(K, 2, 2)`` segments into pieces no longer than ``max_len_m`` (same geometry)."""
    a, b = segments[:, 0], segments[:, 1]
    n_sub = np.maximum(1, np.ceil(np.linalg.norm(b - a, axis=1) / max_len_m).astype(int))
    seg = np.repeat(np.arange(len(segments)), n_sub)
    k = np.arange(len(seg)) - np.repeat(np.cumsum(n_sub) - n_sub, n_sub)
    f0, f1 = (k / n_sub[seg])[:, None], ((k + 1) / n_sub[seg])[:, None]
    d = (b - a)[seg]
    return np.stack([a[seg] + f0 * d, a[seg] + f1 * d], axis=1)


def _point_segment_distances(p: np.ndarray, a: np.ndarray, b: np.ndarray) -> np.ndarray:
    ab = b - a
    len2 = np.einsum("...i,...i->...", ab, ab)
    t = np.clip(np.einsum("...i,...i->...", p - a, ab) / np.where(len2 > 0, len2, 1.0), 0.0, 1.0)
    return np.linalg.norm(a + t[..., None] * ab - p, axis=-1)


PIECE_M = 2.0  # segments are cut into pieces no longer than this for the candidate search
K_FAST = 4  # nearest pieces tried first


def distances_to_segments(points_xy: np.ndarray, segments: np.ndarray, cap_m: float = CD_CAP_M) -> np.ndarray:
    """``(S,)`` exact distance of each point to the nearest of ``segments (K, 2, 2)``, capped at
    ``cap_m`` (also the value for an empty segment set).

    Segments are cut into pieces <= 2 m and indexed by their midpoints (cKDTree). First each
    point tries its 4 nearest pieces; that is provably exact when the 4th midpoint is farther
    than the best distance found plus half a piece. The other points (dense places: many lines
    or copies close by) take every piece whose midpoint lies within ``cap_m`` + half a piece
    (``sparse_distance_matrix``), which contains every piece within ``cap_m``. Exact either way
    (``tests/unit/test_metrics.py`` checks it against shapely) and vectorized.
    """
    points_xy = np.asarray(points_xy, float).reshape(-1, 2)
    out = np.full(len(points_xy), cap_m)
    if len(points_xy) == 0 or len(segments) == 0:
        return out
    pieces = _split_segments(np.asarray(segments, float), PIECE_M)
    half = 0.5 * float(np.linalg.norm(pieces[:, 1] - pieces[:, 0], axis=1).max())
    radius = cap_m + half + 1e-9
    tree_mid = cKDTree(pieces.mean(axis=1))
    # Fast path: the k nearest piece midpoints. Exact for a point whenever the k-th midpoint is
    # farther than (best distance found + half a piece): every other piece is then farther.
    k = min(K_FAST, len(pieces))
    mid_d, mid_i = tree_mid.query(points_xy, k=k, distance_upper_bound=radius)
    mid_d, mid_i = mid_d.reshape(len(points_xy), k), mid_i.reshape(len(points_xy), k)
    valid = mid_i < len(pieces)
    safe = np.where(valid, mid_i, 0)
    d = _point_segment_distances(points_xy[:, None, :], pieces[safe, 0], pieces[safe, 1])
    out = np.minimum(np.where(valid, d, np.inf).min(axis=1), cap_m)
    unsure = np.flatnonzero(valid[:, -1] & (mid_d[:, -1] - half < out))
    if len(unsure):
        # Dense places (many lines or copies near a point): every pair within the radius.
        pairs = cKDTree(points_xy[unsure]).sparse_distance_matrix(tree_mid, radius, output_type="ndarray")
        i, j = pairs["i"], pairs["j"]
        best = np.full(len(unsure), cap_m)
        np.minimum.at(best, i, _point_segment_distances(points_xy[unsure][i], pieces[j, 0], pieces[j, 1]))
        out[unsure] = np.minimum(out[unsure], best)
    return out


def truth_in_corridor(
    features: Sequence[MapFeature],
    true_frames_xy: np.ndarray,
    corridor_m: float = TRUTH_CORRIDOR_M,
    step_m: float = SAMPLE_STEP_M,
) -> tuple[np.ndarray, np.ndarray]:
    """Truth kept within ``corridor_m`` of some true trajectory frame.

    Returns ``(samples_xy (S, 2), segments (K, 2, 2))``: the kept 0.5 m samples, and the truth
    geometry clipped to the corridor as segments between consecutive kept points of the chain
    made of the samples and the original vertices (so it lies exactly on the truth polylines).
    """
    true_frames_xy = np.asarray(true_frames_xy, float).reshape(-1, 2)
    flat = _flatten(features)
    if len(true_frames_xy) == 0 or flat is None:
        return np.zeros((0, 2)), np.zeros((0, 2, 2))
    sample_s, sample_chain = _sample_positions(flat, step_m)
    all_s = np.concatenate([sample_s, flat.s])
    all_chain = np.concatenate([sample_chain, flat.chain])
    is_sample = np.concatenate([np.ones(len(sample_s), bool), np.zeros(len(flat.s), bool)])
    order = np.lexsort((all_s, all_chain))
    all_s, all_chain, is_sample = all_s[order], all_chain[order], is_sample[order]
    pts = flat.at(all_s)
    near = np.isfinite(cKDTree(true_frames_xy).query(pts, distance_upper_bound=corridor_m + 1e-9)[0])
    link = near[:-1] & near[1:] & (all_chain[:-1] == all_chain[1:])
    segs = np.stack([pts[:-1][link], pts[1:][link]], axis=1)
    linked = np.zeros(len(pts), bool)
    linked[:-1] |= link
    linked[1:] |= link
    alone = near & ~linked  # a kept point with no kept neighbour: a zero-length segment
    if alone.any():
        segs = np.concatenate([segs, np.stack([pts[alone], pts[alone]], axis=1)])
    return pts[is_sample & near], segs


@dataclass(frozen=True, slots=True)
class MapTypeScores:
    """Contract map scores of one element type (metres / shares)."""

    cd: float
    completeness: float
    correctness: float
    n_pred_samples: int
    n_truth_samples: int


@dataclass(frozen=True, slots=True)
class MapScores:
    per_type: dict[ElementType, MapTypeScores]
    mcd: float
    # For the error heat map: truth samples and their capped distance to the prediction.
    truth_samples_xy: dict[ElementType, np.ndarray] = field(default_factory=dict)
    truth_sample_error_m: dict[ElementType, np.ndarray] = field(default_factory=dict)


def chamfer_scores(
    pred_features: Sequence[MapFeature], truth_samples_xy: np.ndarray, truth_segments: np.ndarray
) -> tuple[MapTypeScores, np.ndarray]:
    """Contract CD / completeness / correctness of one type; also the per-truth-sample errors."""
    pred_samples = sample_features(pred_features)
    pred_segments = _segments(_as_chains(pred_features))
    d_pred = distances_to_segments(pred_samples, truth_segments)
    d_truth = distances_to_segments(truth_samples_xy, pred_segments)
    if len(pred_samples) == 0 and len(truth_samples_xy) == 0:
        return MapTypeScores(float("nan"), float("nan"), float("nan"), 0, 0), d_truth
    mean_pred = float(d_pred.mean()) if len(d_pred) else CD_CAP_M
    mean_truth = float(d_truth.mean()) if len(d_truth) else CD_CAP_M
    scores = MapTypeScores(
        cd=0.5 * (mean_pred + mean_truth),
        completeness=float(np.mean(d_truth <= MATCH_THRESHOLD_M)) if len(d_truth) else float("nan"),
        correctness=float(np.mean(d_pred <= MATCH_THRESHOLD_M)) if len(d_pred) else float("nan"),
        n_pred_samples=int(len(pred_samples)),
        n_truth_samples=int(len(truth_samples_xy)),
    )
    return scores, d_truth


def map_scores(
    pred: Sequence[MapFeature],
    truth: Sequence[MapFeature],
    true_frames_xy: np.ndarray,
    types: Sequence[ElementType] = tuple(ElementType),
) -> MapScores:
    """Contract section 6 map scores for every type in ``types`` (features in one plane)."""
    per_type, samples, errors = {}, {}, {}
    for etype in types:
        t_feats = [f for f in truth if f.type == etype]
        p_feats = [f for f in pred if f.type == etype]
        t_samples, t_segments = truth_in_corridor(t_feats, true_frames_xy)
        scores, d_truth = chamfer_scores(p_feats, t_samples, t_segments)
        per_type[etype] = scores
        samples[etype], errors[etype] = t_samples, d_truth
    cds = [per_type[t].cd for t in MCD_TYPES if t in per_type and np.isfinite(per_type[t].cd)]
    return MapScores(per_type, float(np.mean(cds)) if cds else float("nan"), samples, errors)


def transform_features(a_T_b: np.ndarray, features: Sequence[MapFeature]) -> tuple[MapFeature, ...]:
    return tuple(
        MapFeature(
            type=f.type,
            points_xy_world=apply_se2(a_T_b, f.points_xy_world),
            style=f.style,
            feature_id=f.feature_id,
            properties=f.properties,
        )
        for f in features
    )


# --- whole evaluation ---------------------------------------------------------------------------


@dataclass(frozen=True, slots=True)
class Evaluation:
    """Everything contract section 6 reports for one reconstruction of one scenario."""

    trips: int
    trips_with_poses: int
    truth_T_est: np.ndarray  # (3,) the global alignment (identity when no poses)
    raw: TrajectoryScores
    aligned: TrajectoryScores
    map_raw: MapScores
    map_aligned: MapScores

    @property
    def coverage(self) -> float:
        return self.trips_with_poses / self.trips if self.trips else float("nan")

    def as_dict(self) -> dict:
        def traj(t: TrajectoryScores) -> dict:
            return {
                "ate_rmse": t.ate.rmse,
                "ate_mean": t.ate.mean,
                "ate_n": t.ate.n,
                "rpe_rmse": t.rpe.rmse,
                "rpe_mean": t.rpe.mean,
                "rpe_n": t.rpe.n,
            }

        def mp(m: MapScores) -> dict:
            return {
                "mcd": m.mcd,
                **{
                    e.value: {
                        "cd": s.cd,
                        "completeness": s.completeness,
                        "correctness": s.correctness,
                        "n_pred_samples": s.n_pred_samples,
                        "n_truth_samples": s.n_truth_samples,
                    }
                    for e, s in m.per_type.items()
                },
            }

        return {
            "trips": self.trips,
            "trips_with_poses": self.trips_with_poses,
            "coverage": self.coverage,
            "truth_T_est": [float(v) for v in self.truth_T_est],
            "raw": traj(self.raw),
            "aligned": traj(self.aligned),
            "map_raw": mp(self.map_raw),
            "map_aligned": mp(self.map_aligned),
        }


def evaluate(
    true_xy_by_key: Mapping[str, np.ndarray],
    est_xy_by_key: Mapping[str, np.ndarray],
    truth_map: Sequence[MapFeature],
    pred_map: Sequence[MapFeature],
) -> Evaluation:
    """Contract section 6 for one scenario; all inputs in the scenario's local plane.

    ``true_xy_by_key`` has every trip; ``est_xy_by_key`` the trips with poses, each with one row
    per uploaded frame (a row-count mismatch raises ``ValueError``: the contract's outputs have
    exactly one row per frame).
    """
    keys = [k for k in true_xy_by_key if k in est_xy_by_key]
    for k in keys:
        if est_xy_by_key[k].shape != true_xy_by_key[k].shape:
            raise ValueError(
                f"{k}: estimate has {len(est_xy_by_key[k])} frames, truth {len(true_xy_by_key[k])}"
            )
    if keys:
        est_all = np.concatenate([est_xy_by_key[k] for k in keys])
        true_all = np.concatenate([true_xy_by_key[k] for k in keys])
        truth_T_est = umeyama_se2(est_all, true_all)
    else:
        truth_T_est = np.zeros(3)
    aligned_xy = {k: apply_se2(truth_T_est, est_xy_by_key[k]) for k in keys}
    true_frames = np.concatenate(list(true_xy_by_key.values())) if true_xy_by_key else np.zeros((0, 2))
    return Evaluation(
        trips=len(true_xy_by_key),
        trips_with_poses=len(keys),
        truth_T_est=truth_T_est,
        raw=trajectory_scores(est_xy_by_key, true_xy_by_key, keys),
        aligned=trajectory_scores(aligned_xy, true_xy_by_key, keys),
        map_raw=map_scores(pred_map, truth_map, true_frames),
        map_aligned=map_scores(transform_features(truth_T_est, pred_map), truth_map, true_frames),
    )


# --- evo cross-check ----------------------------------------------------------------------------


def evo_trajectory_errors(
    est_xy: np.ndarray, true_xy: np.ndarray, timestamps_s: np.ndarray, align: bool
) -> tuple[float, float, float, float]:
    """ATE and contract-RPE of one trip computed with evo: ``(ate_rmse, ate_mean, rpe_rmse, rpe_mean)``.

    - ATE: ``evo.core.metrics.APE(translation_part)``; with ``align`` the estimate is first
      aligned by evo's own Umeyama (``align(correct_scale=False)``), on a deepcopy (evo aligns
      in place; see shared/LIBRARY-NOTES.md section 4).
    - RPE: evo's pairing differs from the contract (evo's ``delta_unit=meters, all_pairs=True``
      picks the frame whose path length is *closest* to delta, possibly under it, and drops
      pairs beyond ``tol``; and evo measures the relative translation in the *estimated body
      frame* of frame ``i``, not in the map plane). To compare like with like we feed evo the
      contract's pairs: a trajectory ``[p_i0, p_j0, p_i1, p_j1, ...]`` with identity
      orientations, evo ``RPE(delta=1 frame, all_pairs=True)``, every other error kept. With
      identity rotations evo's relative translation error is exactly ``|d_est - d_true|``.
    """
    import copy

    from evo.core import metrics as evo_metrics
    from evo.core import trajectory

    def traj(xy: np.ndarray, t: np.ndarray, yaw: np.ndarray | None = None) -> trajectory.PoseTrajectory3D:
        z = np.zeros(len(xy))
        th = np.zeros(len(xy)) if yaw is None else yaw
        return trajectory.PoseTrajectory3D(
            positions_xyz=np.c_[xy[:, 0], xy[:, 1], z],
            orientations_quat_wxyz=np.c_[np.cos(th / 2), z, z, np.sin(th / 2)],
            timestamps=np.asarray(t, float),
        )

    ref, est = traj(true_xy, timestamps_s), traj(est_xy, timestamps_s)
    if align:
        est = copy.deepcopy(est)
        est.align(ref, correct_scale=False)
    ape = evo_metrics.APE(evo_metrics.PoseRelation.translation_part)
    ape.process_data((copy.deepcopy(ref), copy.deepcopy(est)))
    est_xy_used = est.positions_xyz[:, :2]
    i, j = rpe_pair_indices(true_xy)
    inter = np.empty(2 * len(i), int)
    inter[0::2], inter[1::2] = i, j
    t_pairs = np.arange(len(inter), dtype=float)
    rpe = evo_metrics.RPE(
        evo_metrics.PoseRelation.translation_part, delta=1, delta_unit=evo_metrics.Unit.frames, all_pairs=True
    )
    rpe.process_data((traj(true_xy[inter], t_pairs), traj(est_xy_used[inter], t_pairs)))
    rpe_err = np.asarray(rpe.error)[0::2]
    return (
        float(ape.get_statistic(evo_metrics.StatisticsType.rmse)),
        float(ape.get_statistic(evo_metrics.StatisticsType.mean)),
        float(np.sqrt(np.mean(rpe_err**2))),
        float(np.mean(rpe_err)),
    )
