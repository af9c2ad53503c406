"""Dashed dividers re-cut into the lines their dashes form (paper III-C, "keep dashed dividers
as one instance").

On a straight road the tracker sees a dashed divider as one detection per frame: the dashes lie
on each other's chord extension and the within-frame join links them (``tracking``). Where the
line turns (a junction's guide line: 3 m dashes, 6 m gaps, 15-35 m radius) the next dash is metres
off that extension, so every dash becomes a track of its own and splicing drops it as shorter
than the type's minimum; or the tracker chains dashes of two guide lines leaving a junction side by
side into one track, whose splice is cut where it runs across its observations (docs/single-trip.md).

Here, after tracking, every dashed-divider track that one line or one circle does not carry is
split into its dashes (observations of one dash overlap from frame to frame) where the splicer
cannot separate its lines by their offsets from the path: the whole track when it runs across the
path; along the path, the stretch of a junction's length where it holds two lines side by side
(guide lines converging, ``side_by_side_frames``). The units (whole tracks, runs and
dashes) are then chained end to end where one circle carries them: for a gap chord ``c`` of length ``g`` from the end of unit A (its end direction ``d_A``
holding ``h_A`` behind the end: half the chord of a straight dash, 0 on an arc) to the near end of
unit B (direction into B ``d_B``), the tangent-chord angles give the curvature on each side,

    kappa_A = 2 angle(d_A, c) / (2 h_A + g),    kappa_B = 2 angle(c, d_B) / (2 h_B + g),

equal on a circle (zero on a straight line). A dash of a parallel line, or of a guide line that
leaves at an angle, needs a kink or an S: the two disagree. The test is in sigmas
(``TRACK_GATE_SIGMAS``) of the difference, from each unit's direction noise (the spread of its
observations' chord angles, at least the lateral noise prior's ``sqrt(2) sigma / L`` per frame,
over the square root of its frames) and the gap chord's (the lateral noise prior at both ends over
``g``); the common curvature must be no tighter than a car's turning circle, and a gap between two
tracks no longer than the dash gaps the trip saw on its straight lines. Each end takes at most one
link, the nearest consistent one first; chains never close on themselves. A dash seen in too few
frames to be an element links only within its own track.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.cluster.hierarchy import DisjointSet
from scipy.spatial import cKDTree

from csr_core.single_trip.compiled.growth import BEND_MIN_RADIUS_M, kasa_circle
from csr_core.single_trip.params import SingleTripParams
from csr_core.single_trip.tracking import Pieces, Track, component_labels, pair_distance
from csr_core.types import DividerStyle, ElementType

#: the longest dash gap of a trip's lines, as a quantile of the gaps it saw (a missed dash makes
#: a few gaps of two periods)
DASH_GAP_QUANTILE = 0.9
#: a track holding two lines side by side over more tracked frames than this many times the frames
#: one dash stays in view holds two lines running side by side (the splicer separates them by their
#: offsets from the path), not lines converging in a junction
SIDE_BY_SIDE_MAX_VIEWS = 3


@dataclass(frozen=True, slots=True)
class DashChord:
    """A dashed-divider track in the world frame that one line or one circle carries: its two
    ends, the direction at each end pointing out of the track, and how far behind the end that
    direction holds (half the chord of a straight piece: a chord's direction is the tangent at its
    middle; 0 on an arc, whose end tangent is known)."""

    track: int
    ends_xy: np.ndarray  # (2, 2)
    out_dirs: np.ndarray  # (2, 2) unit, out of the track at each end
    behind_m: float
    angle_sigma_rad: float  # of each end direction


def dash_chord(track_index: int, points_w: np.ndarray, params: SingleTripParams) -> DashChord | None:
    """The ends of a track whose observations ``points_w (m, k, 2)`` (world) lie on one line or
    one circle within the tracker's merge gate (``TRACK_MERGE_GATE_M``), the circle no tighter
    than a car's turning circle; ``None`` otherwise (a mixture, a branch, an S)."""
    pts = points_w.reshape(-1, 2)
    n_frames_sigma = np.sqrt(len(points_w))
    centre = pts.mean(axis=0)
    d = pts - centre
    sxx, syy, sxy = d[:, 0] @ d[:, 0], d[:, 1] @ d[:, 1], d[:, 0] @ d[:, 1]
    theta = 0.5 * np.arctan2(2.0 * sxy, sxx - syy)  # principal axis of the 2 x 2 scatter
    u = np.array([np.cos(theta), np.sin(theta)])
    along = d @ u
    across = d @ np.array([-u[1], u[0]])
    length = float(along.max() - along.min())
    if length <= 0.0:
        return None
    if np.abs(across).max() <= params.TRACK_MERGE_GATE_M:
        # straight: its direction from the observations' chords (their spread over the frames,
        # at least the lateral noise prior's)
        chords = points_w[:, -1] - points_w[:, 0]
        obs_len = np.hypot(chords[:, 0], chords[:, 1])
        ok = obs_len > 1e-6
        if not ok.any():
            return None
        dev = np.arctan2(chords[ok] @ np.array([-u[1], u[0]]), chords[ok] @ u)
        dev = (dev + np.pi / 2) % np.pi - np.pi / 2
        prior = np.sqrt(2.0) * params.NOISE_PRIOR_LATERAL_M / np.maximum(obs_len[ok], 1e-6)
        sigma = max(float(np.std(dev)), float(np.median(prior))) / np.sqrt(ok.sum())
        ends = centre + np.outer([along.min(), along.max()], u)
        return DashChord(track_index, ends, np.stack([-u, u]), length / 2.0, sigma)
    c, r2 = kasa_circle(pts)
    if not np.isfinite(r2) or r2 < BEND_MIN_RADIUS_M**2:
        return None
    r = float(np.sqrt(r2))
    rel = pts - c
    if np.abs(np.hypot(rel[:, 0], rel[:, 1]) - r).max() > params.TRACK_MERGE_GATE_M:
        return None
    mid = np.arctan2(*rel.mean(axis=0)[::-1])
    ang = (np.arctan2(rel[:, 1], rel[:, 0]) - mid + np.pi) % (2 * np.pi) - np.pi
    lo, hi = float(ang.min()), float(ang.max())
    if hi - lo >= np.pi:  # more than half a circle: no chord axis orders it
        return None
    ends, dirs = [], []
    for a, sign in ((lo, -1.0), (hi, 1.0)):
        radial = np.array([np.cos(mid + a), np.sin(mid + a)])
        ends.append(c + r * radial)
        dirs.append(sign * np.array([-radial[1], radial[0]]))  # tangent, counter-clockwise for sign +1
    window = min(r * (hi - lo), params.SPLICE_MAX_GAP_M)
    sigma = np.sqrt(2.0) * params.NOISE_PRIOR_LATERAL_M / window / n_frames_sigma
    return DashChord(track_index, np.array(ends), np.array(dirs), 0.0, float(sigma))


def link_costs(
    ends_a: np.ndarray,
    out_a: np.ndarray,
    behind_a: np.ndarray,
    sigma_a: np.ndarray,
    ends_b: np.ndarray,
    out_b: np.ndarray,
    behind_b: np.ndarray,
    sigma_b: np.ndarray,
    params: SingleTripParams,
    max_gap_m: np.ndarray | float,
) -> np.ndarray:
    """Squared sigmas of the curvature mismatch (module docstring) when the ends ``ends_a (P, 2)``
    (direction out of their unit ``out_a``, holding ``behind_a`` behind the end, direction sigma
    ``sigma_a``) continue into the ends ``ends_b`` (likewise); ``inf`` where they cannot be one
    line: not facing each other, gap longer than ``max_gap_m``, turning too tight, or past the
    ``TRACK_GATE_SIGMAS`` gate. Vectorised over the P pairs."""
    chord = ends_b - ends_a
    gap = np.hypot(chord[:, 0], chord[:, 1])
    into_b = -out_b
    ok = (gap > 1e-6) & (gap <= max_gap_m) & ((chord * out_a).sum(1) > 0.0) & ((chord * into_b).sum(1) > 0.0)
    gap = np.where(ok, gap, 1.0)
    w_a, w_b = 2.0 / (2.0 * behind_a + gap), 2.0 / (2.0 * behind_b + gap)
    kappa_a = w_a * np.arctan2(out_a[:, 0] * chord[:, 1] - out_a[:, 1] * chord[:, 0], (out_a * chord).sum(1))
    kappa_b = w_b * np.arctan2(
        chord[:, 0] * into_b[:, 1] - chord[:, 1] * into_b[:, 0], (chord * into_b).sum(1)
    )
    ok &= np.abs(0.5 * (kappa_a + kappa_b)) <= 1.0 / BEND_MIN_RADIUS_M
    chord_sigma = np.sqrt(2.0) * params.NOISE_PRIOR_LATERAL_M / gap
    variance = (w_a * sigma_a) ** 2 + (w_b * sigma_b) ** 2 + ((w_a + w_b) * chord_sigma) ** 2
    z2 = (kappa_a - kappa_b) ** 2 / variance
    return np.where(ok & (z2 <= params.TRACK_GATE_SIGMAS**2), z2, np.inf)


def link_cost(
    a: DashChord, end_a: int, b: DashChord, end_b: int, params: SingleTripParams, max_gap_m: float
) -> float | None:
    """:func:`link_costs` of end ``end_a`` of unit ``a`` into end ``end_b`` of unit ``b``; ``None``
    when they cannot be one line."""
    z2 = link_costs(
        a.ends_xy[end_a][None],
        a.out_dirs[end_a][None],
        np.array([a.behind_m]),
        np.array([a.angle_sigma_rad]),
        b.ends_xy[end_b][None],
        b.out_dirs[end_b][None],
        np.array([b.behind_m]),
        np.array([b.angle_sigma_rad]),
        params,
        max_gap_m,
    )[0]
    return float(z2) if np.isfinite(z2) else None


def observed_dash_gaps_m(pieces: Pieces, tracks: list[Track]) -> np.ndarray:
    """The gaps between consecutive dashes of one line seen in one frame, along the vehicle's x
    axis, over the ``tracks`` that run along the path (the tracker joined their dashes: they lie on
    each other's extension, so the gap is the line's own)."""
    gaps = []
    for track in tracks:
        frame = pieces.frame[track.pieces]
        if len(np.unique(frame)) == len(frame):
            continue  # one piece per frame: no gap seen
        xv = pieces.points_v[track.pieces, :, 0]
        lo, hi = xv.min(axis=1), xv.max(axis=1)
        order = np.lexsort((lo, frame))
        same = frame[order][1:] == frame[order][:-1]
        gap = lo[order][1:] - hi[order][:-1]
        gaps.append(gap[same & (gap > 0.0)])
    return np.concatenate(gaps) if gaps else np.zeros(0)


def _track_of(pieces: Pieces, etype: ElementType, members: np.ndarray) -> Track:
    members = members[np.lexsort((members, pieces.frame[members]))]  # by frame, as the tracker's
    return Track(type=etype, pieces=members, frames=np.unique(pieces.frame[members]))


def runs_across_path(pieces: Pieces, members: np.ndarray, params: SingleTripParams) -> bool:
    """Whether the observations ``members`` run across the vehicle's path: the median over
    those longer than 2 m of |along| / chord in the vehicle frame of their own frame is below
    ``SPLICE_ALONG_GUIDE_MIN`` (the splicer's test, ``splicing._runs_along``, without the path)."""
    chord = pieces.points_v[members, -1] - pieces.points_v[members, 0]
    length = np.hypot(chord[:, 0], chord[:, 1])
    ok = length > 2.0
    return (
        bool(ok.any()) and float(np.median(np.abs(chord[ok, 0]) / length[ok])) < params.SPLICE_ALONG_GUIDE_MIN
    )


def dash_labels(points_w: np.ndarray, params: SingleTripParams) -> np.ndarray:
    """Labels (m,) of the dashes of observations ``points_w (m, k, 2)``: two observations are one
    dash when each one's mean distance to the other is within ``TRACK_MERGE_GATE_M``, with no
    extension along the chord (the next dash, a gap away, is another), and their chords are
    nearly parallel (``TRACK_MAX_ANGLE_RAD``). Only pairs whose middles are within the longer
    one's length are tested."""
    m = len(points_w)
    chord = points_w[:, -1] - points_w[:, 0]
    length = np.hypot(chord[:, 0], chord[:, 1])
    middle = points_w.mean(axis=1)
    pairs = cKDTree(middle).query_pairs(
        float(length.max()) + params.TRACK_MERGE_GATE_M, output_type="ndarray"
    )
    if len(pairs) == 0:
        return np.arange(m)
    a, b = pairs[:, 0], pairs[:, 1]
    near = (
        np.hypot(*(middle[a] - middle[b]).T)
        <= np.maximum(length[a], length[b]) / 2 + params.TRACK_MERGE_GATE_M
    )
    a, b = a[near], b[near]
    u = chord / np.maximum(length, 1e-9)[:, None]
    parallel = (np.abs((u[a] * u[b]).sum(1)) >= np.cos(params.TRACK_MAX_ANGLE_RAD)) | (
        np.minimum(length[a], length[b]) < 2.0
    )
    a, b = a[parallel], b[parallel]
    cap = 3.0 * params.TRACK_MERGE_GATE_M
    ok = np.flatnonzero(
        pair_distance(points_w[b], points_w[a], 0.0, cap).mean(1) <= params.TRACK_MERGE_GATE_M
    )
    ok = ok[pair_distance(points_w[a[ok]], points_w[b[ok]], 0.0, cap).mean(1) <= params.TRACK_MERGE_GATE_M]
    return component_labels(m, a[ok], b[ok])


def side_by_side_frames(pieces: Pieces, members: np.ndarray, params: SingleTripParams) -> np.ndarray:
    """The tracked frames (ascending) in which the observations ``members`` hold two pieces side
    by side: seen over a common stretch ahead of the vehicle (their x ranges in the vehicle frame
    overlap by at least ``SPLICE_BIN_M``) with their middles more than twice the merge gate
    (``TRACK_MERGE_GATE_M``) apart across it. The dashes of one line along the path follow one
    another in x; two lines that the tracker joined into one track (guide lines converging in a
    junction) lie side by side."""
    frame = pieces.frame[members]
    order = np.argsort(frame, kind="stable")
    members, frame = members[order], frame[order]
    start = np.flatnonzero(np.r_[True, frame[1:] != frame[:-1]])
    counts = np.diff(np.r_[start, len(frame)])
    found = []
    for first, n in zip(start[counts > 1].tolist(), counts[counts > 1].tolist(), strict=True):
        pv = pieces.points_v[members[first : first + n]]  # (n, k, 2)
        x_lo, x_hi = pv[..., 0].min(1), pv[..., 0].max(1)
        overlap = np.minimum(x_hi[:, None], x_hi[None, :]) - np.maximum(x_lo[:, None], x_lo[None, :])
        y_mid = pv[..., 1].mean(1)
        apart = np.abs(y_mid[:, None] - y_mid[None, :]) > 2.0 * params.TRACK_MERGE_GATE_M
        if bool((apart & (overlap >= params.SPLICE_BIN_M)).any()):
            found.append(int(frame[first]))
    return np.asarray(found, dtype=np.int64)


def dash_units(pieces: Pieces, track: Track, params: SingleTripParams) -> list[np.ndarray]:
    """The pieces of ``track`` as units for chaining: the whole track when one line or circle
    carries it; its dashes (``dash_labels``) when it runs across the path; when it runs along
    the path, the dashes of the stretch where it holds lines side by side
    (``side_by_side_frames``, widened by the frames one dash stays in view) and the rest as
    whole runs. Along the path the splicer separates a track's lines by their offset from the
    path, except where they converge; split whole, long lines round a roundabout or along a
    highway came out in pieces with the smoothed poses."""
    members = track.pieces
    if dash_chord(0, pieces.points_w[members], params) is not None:
        return [members]
    if runs_across_path(pieces, members, params):
        labels = dash_labels(pieces.points_w[members], params)
        return [members[labels == k] for k in np.unique(labels)]
    mixed = side_by_side_frames(pieces, members, params)
    if not len(mixed):
        return [members]
    x = pieces.points_v[members, :, 0]
    in_view = int(np.ceil(float(x.max() - x.min()) / params.TRACK_STEP_M))  # frames one dash stays in view
    # stretches of mixed frames (gaps shorter than a dash's time in view joined); a stretch longer
    # than a few views is two lines running side by side, which the splicer separates by their
    # offsets from the path
    stretch = np.r_[0, np.cumsum(np.diff(mixed) > in_view)]
    span = np.array([np.ptp(mixed[stretch == k]) for k in range(int(stretch[-1]) + 1)])
    mixed = mixed[span[stretch] <= SIDE_BY_SIDE_MAX_VIEWS * in_view]
    if not len(mixed):
        return [members]
    frame = pieces.frame[members]
    near = np.abs(frame[:, None] - mixed[None, :]).min(axis=1) <= in_view
    units = []
    zone = members[near]
    if len(zone):
        labels = dash_labels(pieces.points_w[zone], params)
        units += [zone[labels == k] for k in np.unique(labels)]
    rest = members[~near]
    run = np.searchsorted(mixed, pieces.frame[rest])  # runs of the track between its mixed stretches
    units += [rest[run == k] for k in np.unique(run)]
    return units


def _attach_leftovers(
    pieces: Pieces,
    units: list[np.ndarray],
    source: list[int],
    chorded: set[int],
    chains: DisjointSet,
    params: SingleTripParams,
) -> None:
    """A unit without a chord (no line or circle fits it: a dash seen partly, a stretch of a long
    line) rejoins the unit of its own track that its points lie on (mean distance within
    ``TRACK_MERGE_GATE_M``): the tracker's association, kept."""
    by_source: dict[int, list[int]] = {}
    for u in sorted(chorded):
        by_source.setdefault(source[u], []).append(u)
    for u in sorted(set(range(len(units))) - chorded):
        if source[u] not in by_source:
            continue
        targets = by_source[source[u]]
        target_pts = [pieces.points_w[units[t]].reshape(-1, 2) for t in targets]
        tree = cKDTree(np.concatenate(target_pts))
        owner = np.repeat(np.arange(len(targets)), [len(p) for p in target_pts])
        dist, idx = tree.query(pieces.points_w[units[u]].reshape(-1, 2))
        best = np.bincount(owner[idx], minlength=len(targets)).argmax()
        if dist[owner[idx] == best].mean() <= params.TRACK_MERGE_GATE_M:
            chains.merge(u, targets[best])


def _link(
    chords: list[DashChord],
    source: list[int],
    weak: list[bool],
    chains: DisjointSet,
    params: SingleTripParams,
    max_gap_m: float,
) -> None:
    """Merge in ``chains`` the units whose ends continue one another (``link_cost``), the nearest
    consistent continuation first, each end once, no loops. Between units of one track (the
    tracker joined them) a gap holds up to the splicer's ``SPLICE_MAX_GAP_M``; between tracks up
    to ``max_gap_m``; a ``weak`` unit links only within its track, over ``max_gap_m`` at most."""
    if len(chords) < 2:
        return
    ends = np.array([c.ends_xy for c in chords]).reshape(-1, 2)  # row 2 c + e: end e of chord c
    outs = np.array([c.out_dirs for c in chords]).reshape(-1, 2)
    behind = np.repeat([c.behind_m for c in chords], 2)
    sigma = np.repeat([c.angle_sigma_rad for c in chords], 2)
    unit = np.repeat([c.track for c in chords], 2)
    src = np.asarray(source)[unit]
    is_weak = np.asarray(weak)[unit]
    pairs = cKDTree(ends).query_pairs(params.SPLICE_MAX_GAP_M, output_type="ndarray")
    ea, eb = pairs[:, 0], pairs[:, 1]
    same = src[ea] == src[eb]
    either_weak = is_weak[ea] | is_weak[eb]
    keep = (unit[ea] != unit[eb]) & (same | ~either_weak)
    ea, eb, same, either_weak = ea[keep], eb[keep], same[keep], either_weak[keep]
    limit = np.where(same & ~either_weak, params.SPLICE_MAX_GAP_M, max_gap_m)
    cost = link_costs(
        ends[ea], outs[ea], behind[ea], sigma[ea], ends[eb], outs[eb], behind[eb], sigma[eb], params, limit
    )
    ok = np.isfinite(cost)
    ea, eb, cost = ea[ok], eb[ok], cost[ok]
    gap = np.hypot(*(ends[ea] - ends[eb]).T)
    candidates = sorted(
        zip(
            gap.tolist(),
            cost.tolist(),
            unit[ea].tolist(),
            (ea % 2).tolist(),
            unit[eb].tolist(),
            (eb % 2).tolist(),
            strict=True,
        )
    )
    used: set[tuple[int, int]] = set()
    for _, _, ua, end_a, ub, end_b in candidates:  # the nearest consistent continuation first
        if (ua, end_a) in used or (ub, end_b) in used or chains.connected(ua, ub):
            continue
        used.update({(ua, end_a), (ub, end_b)})
        chains.merge(ua, ub)


def chain_dash_tracks(
    pieces: Pieces, tracks: list[Track], elements, frames: np.ndarray, params: SingleTripParams
) -> list[Track]:
    """``tracks`` with those of dashed lane dividers re-cut into the lines their dashes form
    (module docstring); the other tracks unchanged. A dashed track that one line or circle
    carries is one unit; any other (a curved line tracked dash by dash, dashes of guide lines
    diverging in a junction assigned to one track) is split into its dashes (``dash_units``).
    Units are then chained end to end where one circle carries them. ``elements``: the trip's per-frame detections, ``frames`` the tracked frames
    (``pieces.frame`` indexes them)."""
    out: list[Track] = []
    dashed: list[Track] = []
    for track in tracks:
        if track.type == ElementType.LANE_DIVIDER:
            styles = [
                elements[frames[f]][j].style
                for f, j in zip(
                    pieces.frame[track.pieces].tolist(), pieces.element[track.pieces].tolist(), strict=True
                )
            ]
            if sum(s == DividerStyle.DASHED for s in styles) * 2 > len(styles):
                dashed.append(track)
                continue
        out.append(track)
    # a link between tracks spans no more than the dash gaps this trip saw on straight dashed
    # lines (a longer "gap" is two lines meeting at a junction), with both ends' along-track noise
    gaps = observed_dash_gaps_m(pieces, [t for t in dashed if not runs_across_path(pieces, t.pieces, params)])
    max_gap_m = params.SPLICE_MAX_GAP_M
    if len(gaps) >= params.TRACK_MIN_FRAMES:
        max_gap_m = min(
            max_gap_m, float(np.quantile(gaps, DASH_GAP_QUANTILE)) + 2.0 * params.NOISE_PRIOR_ALONG_M
        )
    units: list[np.ndarray] = []
    source: list[int] = []  # the dashed track each unit came from
    for k, track in enumerate(dashed):
        split = dash_units(pieces, track, params)
        units += split
        source += [k] * len(split)
    chords = _chords(pieces, units, params)
    chains = DisjointSet(range(len(units)))
    _link(chords, source, _weak(pieces, units, params), chains, params, max_gap_m)
    _attach_leftovers(pieces, units, source, {c.track for c in chords}, chains, params)
    for group in sorted(chains.subsets(), key=min):
        out.append(
            _track_of(pieces, ElementType.LANE_DIVIDER, np.concatenate([units[u] for u in sorted(group)]))
        )
    return out


def _chords(pieces: Pieces, units: list[np.ndarray], params: SingleTripParams) -> list[DashChord]:
    """The chords of the units that one line or circle carries."""
    chords = []
    for i, members in enumerate(units):
        chord = dash_chord(i, pieces.points_w[members], params)
        if chord is not None:
            chords.append(chord)
    return chords


def _weak(pieces: Pieces, units: list[np.ndarray], params: SingleTripParams) -> list[bool]:
    """Units seen in fewer frames than an element on its own needs (``TRACK_MIN_FRAMES``: the
    splicer drops such a track as a false positive): they link only within their own track."""
    return [len(np.unique(pieces.frame[members])) < params.TRACK_MIN_FRAMES for members in units]
