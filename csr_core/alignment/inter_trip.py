"""Algorithm 1, Step 4: inter-trip consistency by a maximum clique (Fig. 7).

Nodes are matching pairs. Two pairs that relate the same two trips (in either order) at places
closer than ``clique_window_m`` measure the same slowly varying relative GNSS error of those
trips, so they are *comparable*, and consistent when their corrections (the displacement of the
circle centre and the rotation) agree within their covariances plus
``clique_consistency_m + clique_drift_m_per_m * d`` (Mahalanobis, chi-square 99.9 %).
An edge joins every consistent or non-comparable pair of nodes, so an absent edge is a proven
contradiction; the maximum weight clique (weights ``int(100 c)``, networkx exact branch and
bound) is the maximum consistent set. Because only pairs of the same two trips are ever
comparable, the clique of the whole graph is the union of the cliques of each trip pair's
subgraph, which is how it is computed (small graphs, exact).

Cycles through three or more trips are checked afterwards by the pose graph's GNC (see
``pose_graph``), where a wrong registration cannot agree with the other trips' registrations.
"""

from __future__ import annotations

from collections import defaultdict
from collections.abc import Sequence
from typing import cast

import networkx as nx
import numpy as np

from csr_core import se2
from csr_core.alignment.association import PairMatch
from csr_core.alignment.params import AlignmentParams

YAW_CONSISTENCY_RAD = 0.01
CHI2_2DOF_999 = 13.8


def correction_of(p: PairMatch, reverse: bool) -> np.ndarray:
    """The registration as a correction of trip_j relative to trip_i at the circle centre
    (translation, yaw); ``reverse`` expresses it as trip_i relative to trip_j."""
    d = se2.inverse(p.delta_local_xyyaw) if reverse else p.delta_local_xyyaw
    return np.asarray(d, float)


def consistent(p: PairMatch, q: PairMatch, params: AlignmentParams) -> bool:
    """Pairwise consistency of two registrations of the same two trips: the difference of the
    corrections, Mahalanobis with both registrations' covariances plus the drift allowance
    (a straight-road registration says nothing along the road, and must not contradict)."""
    dist = float(np.linalg.norm(p.centre_xy_world - q.centre_xy_world))
    if dist > params.clique_window_m:
        return True  # not comparable
    dp = correction_of(p, False)
    dq = correction_of(q, p.trip_i != q.trip_i)
    tol = params.clique_consistency_m + params.clique_drift_m_per_m * dist
    cov_p, cov_q = np.linalg.inv(p.information_local), np.linalg.inv(q.information_local)
    S = cov_p[:2, :2] + cov_q[:2, :2] + tol**2 * np.eye(2)
    d = dp[:2] - dq[:2]
    if float(d @ np.linalg.solve(S, d)) > CHI2_2DOF_999:
        return False
    dyaw = abs(float(se2.wrap_angle(dp[2] - dq[2])))
    return dyaw <= 3.0 * np.sqrt(cov_p[2, 2] + cov_q[2, 2]) + YAW_CONSISTENCY_RAD


def max_consistent_set(pairs: Sequence[PairMatch], params: AlignmentParams) -> list[int]:
    """Indices of the maximum weight clique of the consistency graph of one trip pair."""
    g = nx.Graph()
    for n, p in enumerate(pairs):
        g.add_node(n, w=max(int(round(100 * p.confidence)), 1))
    for a in range(len(pairs)):
        for b in range(a + 1, len(pairs)):
            if consistent(pairs[a], pairs[b], params):
                g.add_edge(a, b)
    clique, _ = nx.max_weight_clique(g, weight="w")
    return sorted(clique)


def inter_trip_consistency(matched: Sequence[PairMatch], params: AlignmentParams) -> list[PairMatch]:
    """Keep the maximum consistent set of every pair of trips."""
    groups: dict[tuple[int, int], list[PairMatch]] = defaultdict(list)
    for p in matched:
        groups[cast(tuple[int, int], tuple(sorted((p.trip_i, p.trip_j))))].append(p)
    out = []
    for group in groups.values():
        out += [group[n] for n in max_consistent_set(group, params)]
    return out
