"""Dash-end landmarks in the sub-map registration (along-road constraint) and the fine stage's
correction spreading."""

from __future__ import annotations

import numpy as np
import pytest

from csr_core import se2
from csr_core.alignment.fine import spread_corrections
from csr_core.alignment.graph_matching import ElementSet
from csr_core.alignment.landmarks import associate_landmarks, landmark_gate_m
from csr_core.alignment.params import AlignmentParams
from csr_core.alignment.registration import LandmarkSets, register_elements
from csr_core.types import ElementType

pytestmark = pytest.mark.unit

P = AlignmentParams()
D, B = ElementType.LANE_DIVIDER, ElementType.ROAD_BOUNDARY
PERIOD_M, DASH_M = 9.0, 3.0  # 3 m dash + 6 m gap


def _straight_road():
    x = np.arange(-25.0, 25.01, 1.0)
    lines = [np.column_stack([x, np.full_like(x, y)]) for y in (-5.25, -1.75, 1.75, 5.25)]
    return ElementSet((B, D, D, B), tuple(lines))


def _dash_ends():
    """Both ends of the dashes of the two dividers: points and direction to the other end."""
    starts = np.arange(-22.0, 20.0, PERIOD_M)
    pts, dirs = [], []
    for y in (-1.75, 1.75):
        for s in starts:
            pts += [[s, y], [s + DASH_M, y]]
            dirs += [[1.0, 0.0], [-1.0, 0.0]]
    return np.asarray(pts), np.asarray(dirs)


def _landmarks(shift_xyyaw, rng):
    tgt, tdir = _dash_ends()
    inv = se2.inverse(np.asarray(shift_xyyaw, float))
    src = se2.transform_points(inv, tgt) + rng.normal(0, 0.03, tgt.shape)
    c, s = np.cos(inv[2]), np.sin(inv[2])
    sdir = tdir @ np.array([[c, -s], [s, c]]).T
    n = len(tgt)
    return LandmarkSets(tgt, tdir, np.full(n, 0.05), src, sdir, np.full(n, 0.05), P.landmark_gate_max_m)


@pytest.mark.parametrize("along_m", [1.2, -2.0])
def test_dash_ends_recover_the_along_road_offset_that_lines_cannot(along_m):
    rng = np.random.default_rng(3)
    truth = np.array([along_m, 0.3, 0.004])
    target = _straight_road()
    inv = se2.inverse(truth)
    source = ElementSet(
        target.types,
        tuple(se2.transform_points(inv, p) + rng.normal(0, 0.03, p.shape) for p in target.points),
    )
    matches = [(k, k) for k in range(4)]
    lines_only = register_elements(target, source, matches, 0.05, P)
    with_marks = register_elements(target, source, matches, 0.05, P, landmarks=_landmarks(truth, rng))
    assert lines_only is not None and with_marks is not None
    # lines fix across and yaw, not along: the along offset stays at the start pose
    assert abs(lines_only.delta_xyyaw[0]) < 0.2 * abs(along_m)
    np.testing.assert_allclose(with_marks.delta_xyyaw, truth, atol=0.03)
    # and the information says so: along is observed only with the landmarks
    assert with_marks.information_xyyaw[0, 0] > 100 * lines_only.information_xyyaw[0, 0]


def test_a_landmark_does_not_snap_to_the_neighbouring_dash():
    """Offset beyond the gate: no association, the along offset is left to the other factors
    (the wrong dash, one period away, must not pull the registration)."""
    rng = np.random.default_rng(4)
    truth = np.array([5.0, 0.0, 0.0])  # the wrong dash end is 4 m away, the right one 5 m
    target = _straight_road()
    source = ElementSet(target.types, tuple(p - truth[:2] for p in target.points))
    reg = register_elements(
        target, source, [(k, k) for k in range(4)], 0.05, P, landmarks=_landmarks(truth, rng)
    )
    assert reg is not None
    assert abs(reg.delta_xyyaw[0]) < 0.5  # neither 5 m (right) nor -4 m (wrong period): not observed
    assert reg.information_xyyaw[0, 0] < 10.0


def test_landmark_gate_stays_below_half_the_dash_period():
    pts, dirs = _dash_ends()
    assert landmark_gate_m(pts, dirs, 100.0) == pytest.approx(0.4 * PERIOD_M)
    assert landmark_gate_m(pts, dirs, 3.0) == 3.0
    # the same end kind associates to the nearest end; the opposite kind never to that end
    idx, ok = associate_landmarks(pts[:1] + [0.1, 0.0], dirs[:1], pts, dirs, 3.0)
    assert ok[0] and idx[0] == 0
    idx, ok = associate_landmarks(pts[:1] + [0.1, 0.0], -dirs[:1], pts, dirs, 3.0)
    assert idx[0] != 0 and np.all(dirs[idx[0]] == -dirs[0])


def test_spread_corrections_interpolates_between_keyframes():
    x = np.linspace(0.0, 100.0, 101)
    poses = np.column_stack([x, np.zeros_like(x), np.zeros_like(x)])
    frames = np.array([0, 50, 100])
    corr = np.array([[0.0, 0.0, 0.0], [0.2, -0.1, 0.0], [0.0, 0.0, 0.0]])
    out = spread_corrections(poses, frames, corr)
    np.testing.assert_allclose(out[[0, 50, 100], :2], poses[[0, 50, 100], :2] + corr[:, :2], atol=1e-12)
    np.testing.assert_allclose(out[25, :2], [25.1, -0.05], atol=1e-12)
    assert np.all(np.abs(np.diff(out[:, 1])) <= 0.1 / 50 + 1e-12)  # no frame-to-frame jumps
