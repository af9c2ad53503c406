"""``evaluate_failures``' per-trip table (the hard-profile rule): a trip with poses that
nothing aligned (``no_overlap``) is shown as such, not as an ordinary aligned trip."""

from __future__ import annotations

import numpy as np
import pytest

from csr_core.alignment.evaluate_failures import format_scores, score_trips

pytestmark = pytest.mark.unit


def test_a_trip_with_its_own_poses_is_shown_unaligned_and_still_judged():
    s = np.linspace(0.0, 100.0, 51)
    road = np.column_stack([s, np.zeros_like(s)])
    true_xy = {"a": road, "b": road + [0.0, 3.5], "lone": road + [0.0, 500.0]}
    yaw = {k: np.zeros(len(s)) for k in true_xy}
    est = {"a": road, "b": road + [0.0, 3.5], "lone": road + [0.0, 500.8]}  # the lone trip 0.8 m off
    scores = score_trips(true_xy, yaw, est, {}, unaligned={"lone": "no_overlap: nothing shares its road"})
    by_key = {x.key: x for x in scores}
    assert by_key["lone"].unaligned_reason.startswith("no_overlap") and by_key["lone"].failed_reason is None
    assert by_key["a"].unaligned_reason is None
    assert by_key["lone"].ate_rmse_m > 0.5
    table = format_scores(scores)
    lone_row = next(line for line in table.splitlines() if line.startswith("lone"))
    assert "unaligned, own poses (no_overlap)" in lone_row and "over bound" in lone_row
    assert table.splitlines()[-1].endswith(
        "unmarked over 0.5 m: 1 (of them unaligned with their own poses: 1)"
    )
