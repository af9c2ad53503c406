"""What a validator can reach (``csr_core.topology.validator_reach``): evidence classes, the
trip-comparison recall ceiling, precision/recall at a bound, and the leave-one-fleet-out
classifiers on properties that do and do not tell the wrong instances apart."""

from __future__ import annotations

import numpy as np
import pytest

from csr_core.topology.validator_reach import (
    ONE_TRIP,
    TRIPS_AGREE,
    TRIPS_DISAGREE,
    best_precision_at_recall,
    best_recall_at_precision,
    evidence_class,
    evidence_table,
    feature_matrix,
    held_out_scores,
    learned_reach,
    precision_recall_points,
    trip_comparison_recall_ceiling,
)

pytestmark = pytest.mark.unit


def _row(
    wrong: bool, suspect: bool = False, support: int = 1, scatter: float = 0.5, rejected: float = 0.0, **extra
) -> dict:
    return {
        "type": "lane_divider",
        "length_m": 30.0,
        "wrong": wrong,
        "suspect": suspect,
        "flags": [],
        "support_trips": support,
        "support_observations": 40,
        "scatter_ratio": scatter,
        "rejected_weight_share": rejected,
        "uncertainty_m": 0.2,
        **extra,
    }


def test_evidence_classes_use_the_validators_own_thresholds():
    assert evidence_class(_row(False, support=1, scatter=5.0)) == ONE_TRIP
    assert evidence_class(_row(False, support=3, scatter=2.5)) == TRIPS_DISAGREE  # > HIGH_VARIANCE_RATIO (2)
    assert evidence_class(_row(False, support=3, rejected=0.3)) == TRIPS_DISAGREE  # >= DISAGREE_WEIGHT_SHARE
    assert evidence_class(_row(False, support=3, scatter=1.9, rejected=0.2)) == TRIPS_AGREE


def test_the_ceiling_leaves_out_the_wrong_lines_that_agreeing_trips_saw():
    rows = (
        [_row(True, suspect=True)] * 6
        + [_row(False, suspect=True)] * 10
        + [_row(True, support=2, scatter=3.0, suspect=True)] * 2
        + [_row(True, support=4)] * 2
        + [_row(False, support=4)] * 80
    )
    table = evidence_table(rows)
    assert table[ONE_TRIP] == {"instances": 16, "wrong": 6, "flagged": 16, "caught": 6}
    assert table[TRIPS_DISAGREE] == {"instances": 2, "wrong": 2, "flagged": 2, "caught": 2}
    assert table[TRIPS_AGREE] == {"instances": 82, "wrong": 2, "flagged": 0, "caught": 0}
    assert trip_comparison_recall_ceiling(table) == pytest.approx(8 / 10)
    assert np.isnan(trip_comparison_recall_ceiling(evidence_table([_row(False)])))


def test_precision_at_recall_and_recall_at_precision_on_a_known_ranking():
    score = np.array([0.9, 0.8, 0.7, 0.6, 0.5, 0.4])
    wrong = np.array([True, False, True, False, True, False])
    assert best_precision_at_recall(score, wrong, 2 / 3) == pytest.approx(2 / 3)  # the top three
    assert best_precision_at_recall(score, wrong, 1.0) == pytest.approx(3 / 5)
    assert best_recall_at_precision(score, wrong, 1.0) == pytest.approx(1 / 3)  # the top one alone
    assert best_recall_at_precision(score, wrong, 0.6) == pytest.approx(1.0)
    # tied scores are flagged together: nothing separates the two, so precision 1 is out of reach
    assert best_recall_at_precision(np.array([1.0, 1.0]), np.array([True, False]), 0.9) == 0.0
    assert np.isnan(best_precision_at_recall(score, np.zeros(6, bool), 0.8))
    rec, prec = precision_recall_points(np.array([0.9, 0.9, 0.5, 0.1]), np.array([True, False, True, False]))
    np.testing.assert_allclose(rec, [0.5, 1.0, 1.0])  # the tied top two flagged together
    np.testing.assert_allclose(prec, [0.5, 2 / 3, 0.5])


def _fleets(separating: bool, seed: int) -> tuple[list[dict], list[str]]:
    """Four fleets of 150 instances, a fifth of them wrong; the wrong ones are far shorter when
    ``separating``, else every property is drawn alike for both."""
    rng = np.random.default_rng(seed)
    rows, fleets = [], []
    for fleet in range(4):
        for _ in range(150):
            wrong = bool(rng.random() < 0.2)
            length = rng.uniform(2, 8) if (wrong and separating) else rng.uniform(10, 200)
            if not separating:
                length = rng.uniform(2, 200)
            rows.append(
                _row(
                    wrong,
                    support=int(rng.integers(1, 4)),
                    scatter=float(rng.uniform(0, 1.5)),
                    length_m=float(length),
                    passed_trips=int(rng.integers(0, 3)),
                    coverage_trips=int(rng.integers(1, 6)),
                )
            )
            fleets.append(f"fleet-{fleet}")
    return rows, fleets


def test_a_property_that_separates_is_found_on_held_out_fleets():
    rows, fleets = _fleets(separating=True, seed=3)
    reach = learned_reach(rows, fleets, 0.8, 0.5)
    for model, v in reach.items():
        assert v["precision_at_recall"] > 0.9, model
        assert v["recall_at_precision"] > 0.9, model


def test_properties_that_do_not_separate_give_the_base_rate():
    rows, fleets = _fleets(separating=False, seed=4)
    base = np.mean([r["wrong"] for r in rows])
    for model, v in learned_reach(rows, fleets, 0.8, 0.5).items():
        assert v["precision_at_recall"] < base + 0.1, model
        assert v["recall_at_precision"] < 0.3, model


def test_features_and_held_out_scores_shapes_and_errors():
    rows, fleets = _fleets(separating=True, seed=5)
    rows[0] = {**rows[0], "type": "road_boundary", "flags": ["low_support"]}
    x = feature_matrix(rows)
    assert x.shape == (600, 7 + 2 + 1 + 2 + 1) and np.isfinite(x).all()
    scores = held_out_scores(rows, fleets, "logistic regression")
    assert scores.shape == (600,) and np.all((scores >= 0) & (scores <= 1))
    with pytest.raises(ValueError, match="fleet names"):
        held_out_scores(rows, fleets[:-1], "boosted trees")
    with pytest.raises(ValueError, match="unknown model"):
        held_out_scores(rows, fleets, "oracle")
