"""What a validator can reach on a judged map (the target bound: recall >= 0.8 at precision >= 0.5).

The validator compares trips with each other (paper III-E: "the obtained instance geometry and
variance of noise"). Two measurements say how far that can go on a map whose instances were
judged against the truth (``evaluate.judged_rows``):

- **Where the wrong instances are** (:func:`evidence_table`). Every instance falls in one
  class by what its trips say of it: one trip saw it (nobody checked it); two or more saw it and
  *disagree* (their scatter exceeds ``HIGH_VARIANCE_RATIO`` times their own sigma, or the robust
  fit rejected ``DISAGREE_WEIGHT_SHARE`` of the weight: the ``high_variance`` and
  ``trips_disagree`` rules); two or more saw it and *agree* within their noise. A wrong instance
  in the last class is wrong by an error all its trips share (the same GNSS bias, the same
  misreading): no comparison of trips shows it, and flagging the class to catch it flags every
  agreeing line. :func:`trip_comparison_recall_ceiling` is the recall of a validator that
  catches every wrong instance outside that class and flags nothing inside it.
- **What the instances' properties tell** (:func:`learned_reach`). A classifier is trained on
  the truth's verdicts and the properties the map serves for each instance (support, coverage,
  trips that drove alongside, uncertainty, scatter, length, type, the validator's own flags),
  on all fleets but one, and scores the held-out fleet (leave one fleet out, as a validator
  meets a fleet it was not tuned on). Pooled over the held-out scores, the best precision at
  which the ranking reaches the recall bound is what any rule on these properties could hope
  for (an upper estimate: the ranking's threshold is chosen on the scores themselves). Two
  models from scikit-learn: a logistic regression (linear rules) and gradient-boosted trees
  (thresholds and their combinations, as hand rules are).
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from csr_core.topology.params import DEFAULT, TopologyParams

#: evidence classes, as :func:`evidence_class` names them
ONE_TRIP, TRIPS_DISAGREE, TRIPS_AGREE = "one trip", "trips disagree", "trips agree"
EVIDENCE_CLASSES = (ONE_TRIP, TRIPS_DISAGREE, TRIPS_AGREE)
#: the served scalar properties a classifier sees (``judged_rows``); lengths and counts of
#: observations on a log scale
NUMERIC_PROPERTIES = (
    "support_trips",
    "coverage_trips",
    "passed_trips",
    "uncertainty_m",
    "scatter_ratio",
    "rejected_weight_share",
    "max_internal_gap_m",
)
LOG_PROPERTIES = ("length_m", "support_observations")
#: models of :func:`learned_reach`
MODELS = ("logistic regression", "boosted trees")


def evidence_class(row: dict, params: TopologyParams = DEFAULT) -> str:
    """What the instance's trips say of it: ``ONE_TRIP``, ``TRIPS_DISAGREE`` or ``TRIPS_AGREE``
    (module docstring; the thresholds are the validator's own)."""
    if int(row.get("support_trips", 1)) <= 1:
        return ONE_TRIP
    if (
        float(row.get("scatter_ratio") or 0.0) > params.HIGH_VARIANCE_RATIO
        or float(row.get("rejected_weight_share") or 0.0) >= params.DISAGREE_WEIGHT_SHARE
    ):
        return TRIPS_DISAGREE
    return TRIPS_AGREE


def evidence_table(rows: Sequence[dict], params: TopologyParams = DEFAULT) -> dict[str, dict[str, int]]:
    """Per evidence class: instances, really wrong, flagged (a suspect flag), flagged and wrong."""
    table = {c: {"instances": 0, "wrong": 0, "flagged": 0, "caught": 0} for c in EVIDENCE_CLASSES}
    for row in rows:
        t = table[evidence_class(row, params)]
        wrong, flagged = bool(row["wrong"]), bool(row["suspect"])
        t["instances"] += 1
        t["wrong"] += wrong
        t["flagged"] += flagged
        t["caught"] += wrong and flagged
    return table


def trip_comparison_recall_ceiling(table: dict[str, dict[str, int]]) -> float:
    """Recall of a validator that flags every wrong instance its trips do not agree on and no
    instance they agree on (``evidence_table``'s classes); NaN without wrong instances."""
    wrong = sum(t["wrong"] for t in table.values())
    return (wrong - table[TRIPS_AGREE]["wrong"]) / wrong if wrong else float("nan")


def feature_matrix(rows: Sequence[dict]) -> np.ndarray:
    """(N, F) features of judged instances: ``NUMERIC_PROPERTIES``, ``LOG_PROPERTIES`` (log1p),
    observations per metre, one column per element type and per flag seen in ``rows``."""
    types = sorted({r["type"] for r in rows})
    flags = sorted({k for r in rows for k in r.get("flags", ())})
    out = np.zeros((len(rows), len(NUMERIC_PROPERTIES) + len(LOG_PROPERTIES) + 1 + len(types) + len(flags)))
    for i, r in enumerate(rows):
        numeric = [float(r.get(k) or 0.0) for k in NUMERIC_PROPERTIES]
        logs = [np.log1p(max(float(r.get(k) or 0.0), 0.0)) for k in LOG_PROPERTIES]
        density = float(r.get("support_observations") or 0.0) / max(float(r.get("length_m") or 0.0), 1.0)
        out[i] = [
            *numeric,
            *logs,
            density,
            *(float(r["type"] == t) for t in types),
            *(float(k in r.get("flags", ())) for k in flags),
        ]
    return out


def precision_recall_points(score: np.ndarray, wrong: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Recall and precision of ``score >= threshold`` at every distinct threshold, highest
    first: ``(recall (T,), precision (T,))``; ties flagged together. Empty without wrong
    instances."""
    wrong = np.asarray(wrong, bool)
    if not wrong.any():
        return np.zeros(0), np.zeros(0)
    score = np.asarray(score, float)
    order = np.argsort(-score, kind="stable")
    caught = np.cumsum(wrong[order])
    flagged = np.arange(1, len(score) + 1)
    last_of_tie = np.r_[score[order][1:] != score[order][:-1], True]
    return caught[last_of_tie] / wrong.sum(), caught[last_of_tie] / flagged[last_of_tie]


def best_precision_at_recall(score: np.ndarray, wrong: np.ndarray, recall: float) -> float:
    """Highest precision of ``score >= threshold`` over thresholds whose recall of ``wrong`` is
    at least ``recall`` (0 when none reaches it, NaN without wrong instances). Ties in ``score``
    are flagged together."""
    rec, prec = precision_recall_points(score, wrong)
    if not len(rec):
        return float("nan")
    ok = rec >= recall - 1e-12
    return float(prec[ok].max()) if ok.any() else 0.0


def best_recall_at_precision(score: np.ndarray, wrong: np.ndarray, precision: float) -> float:
    """Highest recall of ``wrong`` by ``score >= threshold`` over thresholds whose precision is
    at least ``precision`` (0 when none reaches it, NaN without wrong instances)."""
    rec, prec = precision_recall_points(score, wrong)
    if not len(rec):
        return float("nan")
    ok = prec >= precision - 1e-12
    return float(rec[ok].max()) if ok.any() else 0.0


def _model(name: str, seed: int):
    if name == "logistic regression":
        from sklearn.linear_model import LogisticRegression
        from sklearn.pipeline import make_pipeline
        from sklearn.preprocessing import StandardScaler

        return make_pipeline(StandardScaler(), LogisticRegression(max_iter=5000))
    if name == "boosted trees":
        from sklearn.ensemble import HistGradientBoostingClassifier

        return HistGradientBoostingClassifier(
            max_depth=3, max_iter=200, learning_rate=0.05, random_state=seed
        )
    raise ValueError(f"unknown model {name!r}; one of {MODELS}")


def held_out_scores(rows: Sequence[dict], fleets: Sequence[str], model: str, seed: int = 0) -> np.ndarray:
    """Each instance's probability of being wrong from ``model`` trained on the other fleets'
    instances (leave one fleet out); NaN for a fleet whose training set has only one verdict."""
    x = feature_matrix(rows)
    wrong = np.array([bool(r["wrong"]) for r in rows])
    fleet = np.asarray(fleets)
    if len(fleet) != len(rows):
        raise ValueError(f"{len(fleet)} fleet names for {len(rows)} instances")
    scores = np.full(len(rows), np.nan)
    for name in np.unique(fleet):
        train, test = fleet != name, fleet == name
        if len(np.unique(wrong[train])) < 2:
            continue
        scores[test] = _model(model, seed).fit(x[train], wrong[train]).predict_proba(x[test])[:, 1]
    return scores


def learned_reach(
    rows: Sequence[dict], fleets: Sequence[str], recall: float, precision: float, seed: int = 0
) -> dict[str, dict]:
    """Per model of ``MODELS``, from the pooled held-out scores (``held_out_scores``): the best
    precision at ``recall`` (``precision_at_recall``), the best recall at ``precision``
    (``recall_at_precision``; both NaN where no fleet could be scored) and the whole curve
    (``curve``: ``precision_recall_points``)."""
    out: dict[str, dict] = {}
    wrong = np.array([bool(r["wrong"]) for r in rows])
    for model in MODELS:
        scores = held_out_scores(rows, fleets, model, seed)
        ok = np.isfinite(scores)
        if not ok.any():
            out[model] = {
                "precision_at_recall": float("nan"),
                "recall_at_precision": float("nan"),
                "curve": (np.zeros(0), np.zeros(0)),
            }
            continue
        out[model] = {
            "precision_at_recall": best_precision_at_recall(scores[ok], wrong[ok], recall),
            "recall_at_precision": best_recall_at_precision(scores[ok], wrong[ok], precision),
            "curve": precision_recall_points(scores[ok], wrong[ok]),
        }
    return out
