"""Dashes of a curved dashed divider, tracked one by one, chained into one track
(``csr_core.single_trip.dash_chaining``)."""

import numpy as np
import pytest

from csr_core.single_trip.dash_chaining import chain_dash_tracks, dash_chord, link_cost
from csr_core.single_trip.params import DEFAULT
from csr_core.single_trip.tracking import TYPE_CODES, Pieces, Track
from csr_core.types import DividerStyle, ElementType, PerceivedElement

pytestmark = pytest.mark.unit

K = DEFAULT.TRACK_RESAMPLE_POINTS
FRAMES_PER_DASH = 6


def _arc(centre, radius: float, a0: float, a1: float, n: int = K) -> np.ndarray:
    a = np.linspace(a0, a1, n)
    return np.column_stack([centre[0] + radius * np.cos(a), centre[1] + radius * np.sin(a)])


def _line(start, direction_rad: float, s0: float, s1: float, n: int = K) -> np.ndarray:
    s = np.linspace(s0, s1, n)
    return np.asarray(start, float) + np.outer(s, [np.cos(direction_rad), np.sin(direction_rad)])


def _tracks_of(dashes: list[list[np.ndarray]], seed: int = 3):
    """One track per entry of ``dashes`` (its pieces: one dash seen in ``FRAMES_PER_DASH``
    consecutive frames, 3 cm of noise each), as the tracker leaves a curved dashed line; the
    vehicle sits at the origin heading +x in every frame (only ``points_v``'s x-extent is read)."""
    rng = np.random.default_rng(seed)
    frame: list[int] = []
    elements: dict[int, list[PerceivedElement]] = {}
    points, tracks = [], []
    for t, dash_pieces in enumerate(dashes):
        members = []
        for d, dash in enumerate(dash_pieces):
            for f in range(FRAMES_PER_DASH):
                fr = 10 * t + 2 * d + f
                members.append(len(frame))
                frame.append(fr)
                points.append(dash + rng.normal(0.0, 0.03, dash.shape))
                elements.setdefault(fr, []).append(
                    PerceivedElement(ElementType.LANE_DIVIDER, dash, DividerStyle.DASHED)
                )
        index = np.array(members)
        order = np.lexsort((index, np.array(frame)[index]))
        tracks.append(Track(ElementType.LANE_DIVIDER, index[order], np.unique(np.array(frame)[index])))
    n_frames = max(frame) + 1
    element_index = np.zeros(len(frame), dtype=np.int64)
    seen: dict[int, int] = {}
    for q, fr in enumerate(frame):
        element_index[q] = seen.get(fr, 0)
        seen[fr] = element_index[q] + 1
    pw = np.array(points)
    pieces = Pieces(
        np.array(frame),
        element_index,
        np.full(len(frame), TYPE_CODES[ElementType.LANE_DIVIDER]),
        pw.copy(),
        pw,
    )
    return pieces, tracks, [tuple(elements.get(f, ())) for f in range(n_frames)], np.arange(n_frames)


def _guide_line_dashes(centre, radius: float, start_rad: float, turn_rad: float) -> list[np.ndarray]:
    """3 m dashes, 6 m gaps, on a circle (counter-clockwise from ``start_rad``)."""
    step, dash = 9.0 / radius, 3.0 / radius
    return [
        _arc(centre, radius, a, a + dash) for a in np.arange(start_rad, start_rad + turn_rad - dash, step)
    ]


def test_dash_chord_of_a_straight_dash_and_of_an_arc():
    straight = dash_chord(0, np.stack([_line((0, 0), 0.3, 0.0, 3.0)] * 4), DEFAULT)
    assert straight is not None
    assert abs(straight.out_dirs[1] @ [np.cos(0.3), np.sin(0.3)]) == pytest.approx(1.0)
    assert np.allclose(straight.out_dirs[0], -straight.out_dirs[1])
    assert straight.behind_m == pytest.approx(1.5)  # a chord's direction holds at its middle
    arc = dash_chord(0, np.stack([_arc((0, 0), 15.0, 0.0, 1.5, 20)] * 4), DEFAULT)
    assert arc is not None and arc.behind_m == 0.0
    assert np.allclose(arc.ends_xy, [[15.0, 0.0], [15.0 * np.cos(1.5), 15.0 * np.sin(1.5)]], atol=1e-6)
    assert np.allclose(arc.out_dirs[1], [-np.sin(1.5), np.cos(1.5)], atol=1e-6)  # the tangent, onwards
    tight = dash_chord(0, np.stack([_arc((0, 0), 3.0, 0.0, 2.0, 20)] * 4), DEFAULT)
    assert tight is None  # tighter than a car turns: not one marking


def _facing_cost(a, b, max_gap_m: float = 15.0):
    """``link_cost`` between the nearest ends of ``a`` and ``b`` (an end's index follows the sign
    of the chord's principal axis)."""
    gaps = np.hypot(*(a.ends_xy[:, None] - b.ends_xy[None]).transpose(2, 0, 1))
    end_a, end_b = np.unravel_index(np.argmin(gaps), gaps.shape)
    return link_cost(a, int(end_a), b, int(end_b), DEFAULT, max_gap_m)


def test_next_dash_on_the_circle_links_and_a_parallel_or_kinked_one_does_not():
    dashes = _guide_line_dashes((0.0, 0.0), 15.0, 0.0, np.pi)
    chords = [dash_chord(i, np.stack([d] * 4), DEFAULT) for i, d in enumerate(dashes)]
    assert _facing_cost(chords[0], chords[1]) is not None
    parallel = dash_chord(9, np.stack([_arc((0.0, 0.0), 18.5, 9.0 / 18.5, 12.0 / 18.5)] * 4), DEFAULT)
    assert _facing_cost(chords[0], parallel) is None  # the next lane's line
    kinked = dash_chord(
        9, np.stack([_line(dashes[1][0], np.pi / 2 + 9.0 / 15.0 + 0.6, 0.0, 3.0)] * 4), DEFAULT
    )
    assert _facing_cost(chords[0], kinked) is None  # turns 34 degrees more than the arc
    assert _facing_cost(chords[0], chords[1], max_gap_m=5.0) is None  # the gap (6 m) beyond the limit


def test_a_guide_line_tracked_dash_by_dash_becomes_one_track():
    dashes = _guide_line_dashes((0.0, 0.0), 15.0, -0.3, 2.2)
    pieces, tracks, elements, frames = _tracks_of([[d] for d in dashes])
    out = chain_dash_tracks(pieces, tracks, elements, frames, DEFAULT)
    assert len(tracks) == len(dashes) >= 4
    assert len(out) == 1
    assert sorted(out[0].pieces.tolist()) == list(range(len(pieces.frame)))
    assert np.all(np.diff(pieces.frame[out[0].pieces]) >= 0)  # by frame, as the tracker's


def test_two_guide_lines_mixed_in_one_track_are_cut_into_their_lines():
    # two guide lines leaving a junction side by side, 3.5 m apart, and diverging (radii 15 m and
    # 25 m): the tracker chained dashes of both into one track; each line comes out whole, alone
    inner = _guide_line_dashes((0.0, 0.0), 15.0, 0.0, 1.6)
    outer = [d + np.array([-6.5, 0.0]) for d in _guide_line_dashes((0.0, 0.0), 25.0, 0.0, 1.0)]
    pieces, tracks, elements, frames = _tracks_of(
        [inner[:2] + outer[:2], *([d] for d in inner[2:] + outer[2:])]
    )
    out = chain_dash_tracks(pieces, tracks, elements, frames, DEFAULT)
    points = [pieces.points_w[t.pieces].reshape(-1, 2) for t in out]
    radii = [
        np.hypot(p[:, 0] - c, p[:, 1])
        for p, c in ((p, 0.0 if np.hypot(*p.mean(0)) < 18 else -6.5) for p in points)
    ]
    assert len(out) == 2
    assert sorted(len(t.pieces) for t in out) == sorted(
        [len(inner) * FRAMES_PER_DASH, len(outer) * FRAMES_PER_DASH]
    )
    for r in radii:  # every dash on its own circle
        assert np.ptp(np.round(r)) <= 1.0


def test_tracks_of_other_types_and_of_solid_lines_are_left_alone():
    dashes = _guide_line_dashes((0.0, 0.0), 15.0, -0.3, 2.2)
    pieces, tracks, elements, frames = _tracks_of([[d] for d in dashes])
    solid = [
        tuple(PerceivedElement(e.type, e.points_xy_vehicle, DividerStyle.SOLID) for e in f) for f in elements
    ]
    assert chain_dash_tracks(pieces, tracks, solid, frames, DEFAULT) == tracks
    boundaries = [Track(ElementType.ROAD_BOUNDARY, t.pieces, t.frames) for t in tracks]
    assert chain_dash_tracks(pieces, boundaries, elements, frames, DEFAULT) == boundaries


def test_a_mixed_track_along_the_path_is_left_to_the_splicer():
    # the same two lines, but seen along the path (the vehicle follows them): the splicer separates
    # the lines of such a track along the path, so it stays one track here
    inner = _guide_line_dashes((0.0, 0.0), 15.0, 0.0, 1.6)
    outer = [d + np.array([-6.5, 0.0]) for d in _guide_line_dashes((0.0, 0.0), 25.0, 0.0, 1.0)]
    pieces, tracks, elements, frames = _tracks_of(
        [inner[:2] + outer[:2], *([d] for d in inner[2:] + outer[2:])]
    )
    along = np.stack([np.hypot(*pieces.points_w.transpose(2, 0, 1)), np.zeros(pieces.points_w.shape[:2])], -1)
    along[..., 0] += np.linspace(0.0, 3.0, K)  # every observation runs along the vehicle's x axis
    pieces = Pieces(pieces.frame, pieces.element, pieces.type_code, along, pieces.points_w)
    out = chain_dash_tracks(pieces, tracks, elements, frames, DEFAULT)
    assert any(np.array_equal(t.pieces, tracks[0].pieces) for t in out)


def _two_lines_side_by_side(n_frames: int, seed: int = 5):
    """One track holding two straight dashed lines 3.5 m apart (y = 0 and y = 3.5, 3 m dashes,
    6 m gaps, the second line's dashes 1 m further on), as the tracker leaves two lines it joined;
    the vehicle drives along +x, 5 m per tracked frame, and sees the dashes within -15..30 m."""
    rng = np.random.default_rng(seed)
    frame, points_v, points_w, line_of, elements = [], [], [], [], []
    for f in range(n_frames):
        x_vehicle = 5.0 * f
        seen = []
        for line, (y, phase) in enumerate(((0.0, 0.0), (3.5, 1.0))):
            for start in np.arange(phase, 5.0 * n_frames + 40.0, 9.0):
                if -15.0 <= start - x_vehicle and start + 3.0 - x_vehicle <= 30.0:
                    w = _line((start, y), 0.0, 0.0, 3.0) + rng.normal(0.0, 0.03, (K, 2))
                    frame.append(f)
                    points_w.append(w)
                    points_v.append(w - [x_vehicle, 0.0])
                    line_of.append(line)
                    seen.append(
                        PerceivedElement(ElementType.LANE_DIVIDER, w - [x_vehicle, 0.0], DividerStyle.DASHED)
                    )
        elements.append(tuple(seen))
    frame_arr = np.array(frame)
    element_index = np.concatenate([np.arange(np.sum(frame_arr == f)) for f in range(n_frames)])
    pieces = Pieces(
        frame_arr,
        element_index,
        np.full(len(frame), TYPE_CODES[ElementType.LANE_DIVIDER]),
        np.array(points_v),
        np.array(points_w),
    )
    track = Track(ElementType.LANE_DIVIDER, np.arange(len(frame)), np.arange(n_frames))
    return pieces, [track], elements, np.arange(n_frames), np.array(line_of)


def test_two_lines_side_by_side_for_a_junction_s_length_are_cut_into_their_lines():
    # along the path, but side by side over a few frames only (guide lines converging in a
    # junction, which the splicer's offsets from the path do not separate): each line comes out alone
    pieces, tracks, elements, frames, line_of = _two_lines_side_by_side(6)
    out = chain_dash_tracks(pieces, tracks, elements, frames, DEFAULT)
    assert len(out) == 2
    assert sorted(sorted(t.pieces.tolist()) for t in out) == sorted(
        np.flatnonzero(line_of == k).tolist() for k in (0, 1)
    )


def test_two_lines_side_by_side_over_a_long_stretch_are_left_to_the_splicer():
    # side by side over more than three views (two lanes' dividers joined by the tracker over a
    # whole road): the splicer separates them by their offsets from the path; split into dashes,
    # long lines came out in pieces with the smoothed poses
    pieces, tracks, elements, frames, _ = _two_lines_side_by_side(40)
    out = chain_dash_tracks(pieces, tracks, elements, frames, DEFAULT)
    assert len(out) == 1 and np.array_equal(out[0].pieces, tracks[0].pieces)
