"""The lane graph scored against the truth's centrelines: known answers on a T junction."""

import numpy as np
import pytest

from csr_core.topology.evaluate_lane_graph import compare_lane_graphs
from csr_core.topology.params import TopologyParams
from csr_core.types import ElementType, MapFeature

pytestmark = pytest.mark.unit


def _cl(fid, *xy):
    pts = np.concatenate([np.linspace(a, b, 40) for a, b in zip(xy[:-1], xy[1:], strict=True)])
    return MapFeature(ElementType.CENTERLINE, pts, feature_id=fid)


# a through lane in two pieces (0 -> 50 -> 100 m along x) and a turn lane leaving at 50 m
TRUTH = (
    _cl("a", (0, 0), (50, 0)),
    _cl("b", (50, 0), (100, 0)),
    _cl("c", (50, 0), (58, 2), (64, 8), (66, 30)),
)
FRAMES = np.array([(x, 0.0) for x in range(0, 101, 2)] + [(66.0, y) for y in range(0, 31, 2)])


def _scores(features):
    return compare_lane_graphs(features, TRUTH, FRAMES, 12.0, TopologyParams()).scores()


def test_the_truth_scores_itself_perfectly():
    s = _scores(TRUTH)
    assert s["connections"] == s["truth_connections"] == 2
    assert s["connection_precision"] == s["connection_recall"] == 1.0
    assert s["split_precision"] == s["split_recall"] == 1.0


def test_a_through_lane_fused_into_one_piece_still_connects_the_same_way():
    s = _scores((_cl("ab", (0, 0), (100, 0)), TRUTH[2]))
    assert s["connection_precision"] == s["connection_recall"] == 1.0
    assert s["split_recall"] == 1.0


def test_a_missing_turn_lane_and_a_wrong_one_are_counted():
    # the turn lane is gone; a lane that no truth lane continues into leaves at 20 m instead
    s = _scores((TRUTH[0], TRUTH[1], _cl("w", (20, 0), (28, -2), (34, -8), (36, -30))))
    assert s["connection_recall"] == pytest.approx(0.5)  # a -> b kept, a -> c lost
    assert s["connection_precision"] < 1.0  # the split at 20 m has no truth counterpart
    assert s["split_recall"] == 0.0 and s["split_precision"] == 0.0


def test_lanes_cut_shorter_than_the_lookahead_are_followed_into_their_successors():
    # the truth's through lane in 5.5 m pieces (lanelet borders), ours in one: 10 m on is the same place
    pieces = tuple(_cl(f"p{k}", (x, 0), (x + 5.5, 0)) for k, x in enumerate(np.arange(0.0, 99.0, 5.5)))
    s = compare_lane_graphs((_cl("ab", (0, 0), (100, 0)),), pieces, FRAMES, 12.0, TopologyParams()).scores()
    assert s["truth_connections"] == 17
    assert s["connection_recall"] == 1.0
    # and the other way round: our lane in pieces against the truth in one
    s = compare_lane_graphs(pieces, (_cl("ab", (0, 0), (100, 0)),), FRAMES, 12.0, TopologyParams()).scores()
    assert s["connection_precision"] == 1.0


def test_the_comparison_is_drawn(tmp_path):
    from csr_core.topology.evaluate_lane_graph import plot_comparison

    # the wrong turn of the test above: one truth connection missed, one map connection false
    cmp = compare_lane_graphs(
        (TRUTH[0], TRUTH[1], _cl("w", (20, 0), (28, -2), (34, -8), (36, -30))),
        TRUTH,
        FRAMES,
        12.0,
        TopologyParams(),
    )
    assert (~cmp.got).sum() == 1 and (~cmp.right).sum() >= 1
    out = tmp_path / "lane_graph.png"
    plot_comparison(cmp, out, (0.0, 100.0, -35.0, 35.0))
    assert out.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
