"""The trajectory figure's layering: the estimates drawn over the truth, the truth thin and dashed."""

import matplotlib

matplotlib.use("Agg")

import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
import pytest  # noqa: E402
from numpy.testing import assert_allclose  # noqa: E402

from csr_core.bench.figures import draw_trajectories  # noqa: E402

pytestmark = pytest.mark.unit


def test_estimates_are_drawn_above_a_thin_dashed_truth():
    x_m = np.linspace(0.0, 30.0, 31)
    true_xy = {
        "a": np.column_stack([x_m, np.zeros_like(x_m)]),
        "b": np.column_stack([x_m, np.full_like(x_m, 3.5)]),
    }
    est_xy = {k: xy + [0.0, 0.2] for k, xy in true_xy.items()}  # right on the truth: hidden under it if below
    truth_T_est = np.array([1.0, -0.2, 0.0])  # metres, metres, radians
    fig, ax = plt.subplots()
    try:
        lines = draw_trajectories(ax, true_xy, est_xy, truth_T_est)
        assert [len(lines[k]) for k in ("truth", "raw", "aligned")] == [2, 2, 2]
        # the aligned estimate is the raw one moved by truth_T_est (known answer)
        assert_allclose(lines["aligned"][0].get_xydata(), true_xy["a"] + [1.0, 0.0])
        truth, estimates = lines["truth"], lines["raw"] + lines["aligned"]
        assert max(t.get_zorder() for t in truth) < min(e.get_zorder() for e in estimates)
        assert max(r.get_zorder() for r in lines["raw"]) < min(a.get_zorder() for a in lines["aligned"])
        # matplotlib draws an axes' artists in ascending zorder: every truth line before any estimate
        order = sorted(ax.get_lines(), key=lambda artist: artist.get_zorder())
        drawn_truth = [order.index(t) for t in truth]
        assert max(drawn_truth) < min(order.index(e) for e in estimates)
        # the truth: thin and dashed, thinner than every estimate
        for t in truth:
            assert t.get_linestyle() == "--"
            assert t.get_linewidth() < min(e.get_linewidth() for e in estimates)
        for e in estimates:
            assert e.get_linestyle() == "-"
    finally:
        plt.close(fig)
