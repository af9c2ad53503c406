"""Alignment Step 1-2: topology descriptors (Eq. 3), similarities (Eq. 5/6), RRWM (Eq. 4),
GNC registration, and the one-lane-offset known answer."""

from __future__ import annotations

import numpy as np
import pytest

from csr_core import se2
from csr_core.alignment.association import match_pair
from csr_core.alignment.graph_matching import (
    ElementSet,
    _prune,
    edge_similarity,
    element_distances,
    eq4_objective,
    node_similarity,
    overlap_matrix,
    principal_directions,
    rrwm,
    rrwm_match,
)
from csr_core.alignment.params import AlignmentParams, NoiseScales
from csr_core.alignment.registration import register_elements
from csr_core.alignment.submaps import Circle, Submap, SubmapElement
from csr_core.alignment.topology import (
    TopologyDescriptor,
    cross_section,
    descriptor_at,
    same_road_consistent,
    sliding_window_vote,
    topology_consistent,
    topology_descriptor,
    topology_filter,
)
from csr_core.types import ElementType
from tests.unit.test_alignment_synthetic import LANE_W

pytestmark = pytest.mark.unit

P = AlignmentParams()
NOISE = NoiseScales({t: 0.05 for t in ElementType}, 0.1, sigma_p_m=0.8, sigma_e_m=0.3)
D, B, C = ElementType.LANE_DIVIDER, ElementType.ROAD_BOUNDARY, ElementType.CENTERLINE


def straight_road(offsets_types, x0=-25.0, x1=25.0, spacing=2.0) -> ElementSet:
    x = np.arange(x0, x1 + 1e-9, spacing)
    return ElementSet(
        tuple(t for _, t in offsets_types),
        tuple(np.column_stack([x, np.full_like(x, o)]) for o, _ in offsets_types),
    )


ROAD = [(-7.5, B), (-3.5, D), (0.0, D), (3.5, D), (7.5, B), (-5.25, C), (-1.75, C), (1.75, C), (5.25, C)]


def test_node_similarity_eq5_known_values():
    a = straight_road([(0.0, D), (3.5, B)])
    same = node_similarity(a, a, NOISE, P)
    assert same[0, 0] == pytest.approx(1.0) and same[1, 1] == pytest.approx(1.0)
    assert same[0, 1] == 0.0 and same[1, 0] == 0.0  # different types never match
    shifted = node_similarity(a, a.shifted(np.array([0.0, NOISE.sigma_p_m])), NOISE, P)
    w = P.node_position_weight
    assert shifted[0, 0] == pytest.approx(w * np.exp(-0.5) + (1 - w), abs=1e-6)
    half = ElementSet(a.types[:1], (a.points[0][a.points[0][:, 0] >= 0],))  # half the extent
    s = node_similarity(a, half, NOISE, P)[0, 0]
    d_o = 1 - 2 * 25 / 75  # overlap ratio o_in/(o_in+o_out) = 2/3
    assert s == pytest.approx(w + (1 - w) * np.exp(-0.5 * (d_o / P.sigma_o) ** 2), abs=0.02)


def test_edge_similarity_eq6_known_values():
    e = element_distances(straight_road([(0.0, D), (3.5, D), (7.0, D)]))
    assert e[0, 1] == pytest.approx(3.5) and e[0, 2] == pytest.approx(7.0)
    sim = edge_similarity(e, e + 0.3, 0.3)
    assert sim[0, 1, 0, 1] == pytest.approx(np.exp(-0.5))
    assert edge_similarity(e, e, 0.3)[0, 2, 0, 2] == pytest.approx(1.0)


def test_rrwm_recovers_a_permutation_and_agrees_with_pygmtools():
    rng = np.random.default_rng(0)
    n = 12
    pts = rng.uniform(0, 30, (n, 2))
    perm = rng.permutation(n)
    pts2 = (pts + rng.normal(0, 0.2, pts.shape))[perm]
    D1 = np.linalg.norm(pts[:, None] - pts[None], axis=2)
    D2 = np.linalg.norm(pts2[:, None] - pts2[None], axis=2)
    E = np.exp(-((D1[None, :, None, :] - D2[:, None, :, None]) ** 2) / 2.0)
    E *= (1 - np.eye(n))[None, :, None, :] * (1 - np.eye(n))[:, None, :, None]
    K = E.reshape(n * n, n * n)
    X = rrwm(K, n, n)
    assert X.shape == (n, n)
    assert np.array_equal(np.argmax(X, axis=1), np.argsort(perm))
    pygm = pytest.importorskip("pygmtools")
    pygm.set_backend("numpy")
    ref = pygm.rrwm(K, n, n)
    assert np.array_equal(np.argmax(ref, axis=1), np.argmax(X, axis=1))


def test_rrwm_match_keeps_geometry_consistent_matches_and_drops_dissimilar():
    a = straight_road(ROAD)
    b = straight_road(ROAD).shifted(np.array([0.0, 0.4]))
    s = node_similarity(a, b, NOISE, P)
    m = rrwm_match(s, element_distances(a), element_distances(b), NOISE.sigma_e_m, P)
    assert sorted(m) == [(k, k) for k in range(len(ROAD))]


def test_gnc_registration_recovers_a_rigid_transform_despite_outlier_matches():
    rng = np.random.default_rng(1)
    curve = lambda o: np.column_stack([np.arange(-25, 26, 2.0), o + 0.004 * np.arange(-25, 26, 2.0) ** 2])  # noqa: E731
    types = (B, D, D, D, B, ElementType.STOP_LINE)
    stop = np.column_stack([np.full(8, 10.0), np.linspace(-7, 0, 8)])
    target = ElementSet(types, tuple([curve(o) for o in (-7.5, -3.5, 0.0, 3.5, 7.5)] + [stop]))
    truth = np.array([0.6, -0.8, 0.01])  # source = truth^-1 (target)
    inv = se2.inverse(truth)
    source = ElementSet(
        types, tuple(se2.transform_points(inv, p) + rng.normal(0, 0.03, p.shape) for p in target.points)
    )
    matches = [(0, 0), (1, 1), (2, 2), (3, 3), (4, 4), (5, 5), (1, 2), (3, 1)][:6]
    matches = matches + [(0, 4)]  # outlier: left boundary to right boundary
    reg = register_elements(target, source, matches, 0.05, P)
    assert reg is not None
    np.testing.assert_allclose(reg.delta_xyyaw, truth, atol=0.03)
    assert reg.element_inlier.tolist() == [True] * 6 + [False]


def _submap(es: ElementSet, trip: int, sid: int, pose=(0.0, 0.0, 0.0)) -> Submap:
    """A sub-map whose elements are ``es`` in the world, anchored at ``pose``."""
    inv = se2.inverse(np.asarray(pose, float))
    return Submap(
        sid,
        0,
        trip,
        f"v{trip}__t",
        0,
        0,
        10,
        np.asarray(pose, float),
        tuple(
            SubmapElement(t, se2.transform_points(inv, p), n)
            for n, (t, p) in enumerate(zip(es.types, es.points, strict=False))
        ),
    )


def test_a_sub_map_offset_by_exactly_one_lane_width_is_not_matched_to_the_wrong_lane():
    circle = Circle(0, np.zeros(2), 0.0, 25.0)
    noise = NoiseScales(
        {t: 0.05 for t in ElementType} | {B: 0.1},
        0.1,
        sigma_p_m=2.5 * np.sqrt(2 * 0.05**2 + 0.1**2) + 0.4,
        sigma_e_m=0.25,
    )
    a = straight_road(ROAD)
    b = straight_road(ROAD).shifted(np.array([0.0, LANE_W]))  # initial poses one lane apart
    m = match_pair(_submap(a, 0, 0), _submap(b, 1, 1), circle, noise, P)
    assert m is not None
    assert m.delta_local_xyyaw[1] == pytest.approx(-LANE_W, abs=0.1)  # brought back, not "aligned" as is
    for k, kp in m.element_matches:
        assert abs(np.mean(a.points[k][:, 1]) - (np.mean(b.points[kp][:, 1]) - LANE_W)) < 0.2


def test_without_boundaries_a_one_lane_offset_is_rejected_or_recovered_never_half_matched():
    circle = Circle(0, np.zeros(2), 0.0, 25.0)
    lanes_only = [r for r in ROAD if r[1] != B]
    a = straight_road(lanes_only)
    b = straight_road(lanes_only).shifted(np.array([0.0, LANE_W]))
    m = match_pair(_submap(a, 0, 0), _submap(b, 1, 1), circle, NOISE, P)
    if m is not None:
        assert abs(m.delta_local_xyyaw[1] - (-LANE_W)) < 0.1 or abs(m.delta_local_xyyaw[1]) < 0.1


def test_topology_descriptors_and_eq3_thresholds():
    circle = Circle(0, np.zeros(2), 0.0, 25.0)
    full = topology_descriptor(_submap(straight_road(ROAD), 0, 0), circle, 0.5)
    assert full.lane_count == 4 and full.road_width_m == pytest.approx(15.0)
    assert full.road_centre_m == pytest.approx(0.0) and full.split_merge_count == 0
    narrow = topology_descriptor(_submap(straight_road([(-3.5, B), (0.0, D), (3.5, B)]), 1, 1), circle, 0.5)
    assert narrow.lane_count == 2
    assert not topology_consistent(full, narrow, NOISE, P)
    shifted = topology_descriptor(
        _submap(straight_road(ROAD).shifted(np.array([0.0, 0.5])), 1, 1), circle, 0.5
    )
    assert topology_consistent(full, shifted, NOISE, P)
    far = topology_descriptor(
        _submap(straight_road(ROAD).shifted(np.array([0.0, 12.0])), 1, 1, (0.0, 12.0, 0.0)), circle, 0.5
    )
    assert not topology_consistent(full, far, NOISE, P)  # a parallel road, not the same one


def test_eq3_compares_each_carriageway_with_itself():
    """Two trips on the two carriageways of a divided road (medians' boundaries 4 m apart): each
    sub-map shows its own carriageway whole and of the other only the near boundary. Their own
    roads differ by the median (road centres 19 m apart), which failed every such pair; compared
    at each vehicle's position, each carriageway is compared with itself, or skipped where the
    other sub-map does not show it whole. A view of the same carriageway with a lane missing
    still fails."""
    circle = Circle(0, np.zeros(2), 0.0, 25.0)
    north = [(o + 19.0, t) for o, t in ROAD] + [(7.5, B)]  # and the southern carriageway's near boundary
    south = straight_road(ROAD + [(11.5, B)])
    a = cross_section(_submap(south, 0, 0), circle)
    b = cross_section(_submap(straight_road(north), 1, 1, (0.0, 19.0, 0.0)), circle)
    assert a.vehicle_m == pytest.approx(0.0) and b.vehicle_m == pytest.approx(19.0)
    assert not topology_consistent(
        descriptor_at(a, a.vehicle_m, 0.5), descriptor_at(b, b.vehicle_m, 0.5), NOISE, P
    )
    assert same_road_consistent(a, b, 0.5, 0.5, NOISE, P)
    # the same carriageway with two of its dividers unseen in the other sub-map: 2 lanes against 4,
    # beyond Eq. 3's lane tolerance of 1
    fewer = cross_section(_submap(straight_road([r for r in ROAD if r[0] not in (-3.5, 0.0)]), 1, 1), circle)
    assert not same_road_consistent(a, fewer, 0.5, 0.5, NOISE, P)
    assert same_road_consistent(
        a, cross_section(_submap(straight_road(ROAD), 1, 1), circle), 0.5, 0.5, NOISE, P
    )


def test_a_trip_that_only_meets_the_other_carriageway_is_read_on_the_same_road():
    """Step 1 reads each vehicle's own road first; a trip none of whose pairs pass that (each
    carriageway of a divided road with only the other's trips) has its pairs read again on the
    same road, and only such a trip: a trip that meets its own carriageway keeps the first reading."""
    from types import SimpleNamespace

    circle = Circle(0, np.zeros(2), 0.0, 25.0)
    south = straight_road(ROAD + [(11.5, B)])
    north = straight_road([(o + 19.0, t) for o, t in ROAD] + [(7.5, B)])
    trips = [SimpleNamespace(pose_sigma_xy_m=np.full(20, 0.3)) for _ in range(4)]
    subs = [
        _submap(south, 0, 0),
        _submap(north, 1, 1, (0.0, 19.0, 0.0)),
        _submap(south, 2, 2, (0.0, 0.3, 0.0)),
        _submap(north, 3, 3, (0.0, 19.2, 0.0)),
    ]
    # two trips, one per carriageway: the across pair passes on the second reading
    assert topology_filter([(0, 1)], subs, [circle], trips, NOISE, P).tolist() == [True]
    # trip 1 alone on the north carriageway, trips 0 and 2 together on the south one
    assert topology_filter([(0, 1), (0, 2), (1, 2)], subs, [circle], trips, NOISE, P).tolist() == [True] * 3
    # both carriageways have two trips each: the across pairs keep the own-road reading
    assert topology_filter([(0, 1), (0, 2), (1, 3)], subs, [circle], trips, NOISE, P).tolist() == [
        False,
        True,
        True,
    ]


def test_split_merge_counts_are_compared_within_their_counting_noise():
    """Eq. 3's tau_sm: element ends inside a circle are counted events (a junction's pieces, a
    track broken by occlusion), so two sightings of one junction differ by about
    sqrt(N_i + N_j); a straight road against a junction still fails."""

    def desc(n_ends: int) -> TopologyDescriptor:
        return TopologyDescriptor(-1, float("nan"), n_ends, float("nan"), 0.2)

    assert topology_consistent(desc(17), desc(10), NOISE, P)  # one junction, two trips: 7 <= 2 sqrt(27)
    assert topology_consistent(desc(23), desc(31), NOISE, P)
    assert not topology_consistent(
        desc(0), desc(6), NOISE, P
    )  # 6 > 2 sqrt(6): a junction is not a plain road
    assert not topology_consistent(desc(1), desc(12), NOISE, P)
    assert topology_consistent(desc(0), desc(3), NOISE, P)  # the fixed floor tau_sm = 3 still holds
    fixed = AlignmentParams(topo_split_merge_z=0.0)  # the count's own noise left out: a fixed tau_sm
    assert not topology_consistent(desc(17), desc(10), NOISE, fixed)


def test_sliding_window_vote_drops_isolated_passes():
    votes = np.array([1, 1, 0, 1, 1, 0, 0, 1, 0, 0], bool)
    keys = [("a", "b")] * 10
    out = sliding_window_vote(keys, np.arange(10), votes, half_window=2, min_fraction=0.5)
    assert out.tolist() == [1, 1, 0, 1, 0, 0, 0, 0, 0, 0]


def _pruned_one_at_a_time(matches, s_node, e_a, e_b, sigma_e):
    """Greedy pruning written out: every removal's Eq. 4 value from ``eq4_objective`` itself."""
    matches = list(matches)
    best = eq4_objective(matches, s_node, e_a, e_b, sigma_e, P)
    while len(matches) > 1:
        trials = [
            eq4_objective(matches[:q] + matches[q + 1 :], s_node, e_a, e_b, sigma_e, P)
            for q in range(len(matches))
        ]
        q = int(np.argmax(trials))
        if trials[q] <= best + 1e-9:
            break
        best = trials[q]
        matches.pop(q)
    return matches


def test_greedy_pruning_agrees_with_the_eq4_objective_removal_by_removal():
    rng = np.random.default_rng(4)
    n_pruned = 0
    for _ in range(300):
        n = int(rng.integers(2, 12))
        e_a = rng.random((n, n)) * 20.0
        e_a = e_a + e_a.T
        e_b = e_a + rng.normal(0.0, rng.choice([0.1, 1.0, 3.0]), (n, n))
        e_b = e_b + e_b.T
        np.fill_diagonal(e_a, 0.0)
        np.fill_diagonal(e_b, 0.0)
        s_node = rng.random((n, n))
        matches = [(k, int(kp)) for k, kp in enumerate(rng.permutation(n))][: int(rng.integers(2, n + 1))]
        expected = _pruned_one_at_a_time(matches, s_node, e_a, e_b, 0.5)
        assert _prune(list(matches), s_node, e_a, e_b, 0.5, P) == expected
        n_pruned += len(expected) < len(matches)
    assert n_pruned >= 30  # the cases exercise the pruning, not only its stop


def test_principal_directions_are_the_svd_axes_and_overlap_uses_them():
    rng = np.random.default_rng(5)
    sets = [
        se2.transform_points(
            np.array([0.0, 0.0, rng.uniform(-3.0, 3.0)]),
            rng.normal(0.0, 1.0, (int(rng.integers(2, 30)), 2)) * rng.uniform(0.2, 5.0, 2),
        )
        for _ in range(50)
    ]
    closed_form = principal_directions(sets)
    for pts, d in zip(sets, closed_form, strict=True):
        axis = np.linalg.svd(pts - pts.mean(axis=0), full_matrices=False)[2][0]
        assert abs(float(axis @ d)) == pytest.approx(1.0, abs=1e-9)
    np.testing.assert_allclose(principal_directions([np.array([[3.0, 4.0]])]), [[1.0, 0.0]])
    # a 20 m divider and a 10 m piece of it, shifted 5 m along: half of the union overlaps
    long_ = ElementSet((D,), (np.column_stack([np.arange(0.0, 20.1, 1.0), np.zeros(21)]),))
    piece = ElementSet(
        (D, B),
        (
            np.column_stack([np.arange(15.0, 25.1, 1.0), np.full(11, 0.1)]),
            np.column_stack([np.arange(0.0, 20.1, 1.0), np.full(21, 3.0)]),
        ),
    )
    np.testing.assert_allclose(overlap_matrix(long_, piece), [[2 * 5.0 / 30.0, 0.0]])
