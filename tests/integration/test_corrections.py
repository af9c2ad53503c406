"""Human correction: a deliberately wrong match pair is forced into a tile, which bends a
trip by metres where the pair is; undoing it brings the tile back to the accuracy it had; rejecting an automatic pair
re-optimizes the tile; every correction is audited with the version it made; roles are enforced."""

from __future__ import annotations

import numpy as np
import pytest

from csr_core.bench.evaluate import evaluate_output
from services import fleet
from tests.integration.conftest import wait_until
from tests.integration.test_tile_pipeline import _run_fleet, fleet_dirs  # noqa: F401 (module fixture)

pytestmark = pytest.mark.integration


def _settle(dep, http) -> None:
    wait_until(
        lambda: (s := http.get("/v1/jobs/summary").json())["queued"] == 0 and s["running"] == 0,
        timeout_s=300,
        what="the correction's jobs",
    )


def _trip_error_m(out_dir, scenario, key) -> float:
    """Aligned ATE RMSE of one trip (after the contract's global rigid fit)."""
    ev = evaluate_output(scenario, out_dir)
    from csr_core.metrics import apply_se2

    est = apply_se2(ev.evaluation.truth_T_est, ev.est_xy_by_key[key])
    return float(np.sqrt(np.mean(np.sum((est - ev.true_xy_by_key[key]) ** 2, axis=1))))


def _pair_offset_m(out_dir, scenario, key_i, frames_i, key_j, frames_j) -> np.ndarray:
    """Mean position error (x, y; after the global rigid fit) of trip j over its frames
    ``frames_j`` (first, last) minus that of trip i over ``frames_i``: how far the pair's two
    sub-maps sit from where they truly are relative to each other."""
    ev = evaluate_output(scenario, out_dir)
    from csr_core.metrics import apply_se2

    def mean_error(key, frames):
        est = apply_se2(ev.evaluation.truth_T_est, ev.est_xy_by_key[key])
        return (est - ev.true_xy_by_key[key])[frames[0] : frames[1] + 1].mean(axis=0)

    return mean_error(key_j, frames_j) - mean_error(key_i, frames_i)


def test_a_forced_wrong_pair_bends_the_tile_and_undoing_it_restores_it(make_isolated, fleet_dirs, tmp_path):  # noqa: F811
    dep = make_isolated("embedded")
    dep.start_server()
    run = _run_fleet(dep, fleet_dirs["first"], tmp_path / "before")
    ids = run["ids"]
    by_id = {v: k for k, v in ids.items()}
    with dep.admin() as http:
        tiles = dep.rows("SELECT z, x, y FROM tile_versions ORDER BY n_features DESC")
        z, x, y = tiles[0]
        pairs = http.get(f"/v1/tiles/{z}/{x}/{y}/match-pairs").raise_for_status().json()["match_pairs"]
        pair = next(p for p in pairs if p["trip_i"] and p["trip_j"])
        victim = by_id[pair["trip_j"]]
        other = by_id[pair["trip_i"]]
        before = _trip_error_m(tmp_path / "before", fleet_dirs["first"], victim)
        where = (other, pair["frames_i"], victim, pair["frames_j"])
        offset_before = _pair_offset_m(tmp_path / "before", fleet_dirs["first"], *where)

        # a wrong pair: j's data asserted 3.5 m (a lane) to the side of where it matches i's
        wrong = {
            "kind": "add_pair",
            "trip_i": pair["trip_i"],
            "frames_i": pair["frames_i"],
            "trip_j": pair["trip_j"],
            "frames_j": pair["frames_j"],
            "offset_xyyaw": [0.0, 3.5, 0.0],
            "note": "test: deliberately wrong",
        }
        answer = http.post(f"/v1/tiles/{z}/{x}/{y}/corrections", json=wrong)
        assert answer.status_code == 202, answer.text
        correction = answer.json()
        _settle(dep, http)
        fleet.download_results(http, ids, tmp_path / "wrong", fleet.scenario_bbox(fleet_dirs["first"]))
        bent = _trip_error_m(tmp_path / "wrong", fleet_dirs["first"], victim)
        # the two sub-maps are pulled apart by most of the 3.5 m the pair asserts (the trips'
        # other pairs pull back); the victim trip as a whole is off by more than before
        moved = float(
            np.linalg.norm(_pair_offset_m(tmp_path / "wrong", fleet_dirs["first"], *where) - offset_before)
        )
        assert moved > 0.5 * 3.5, (moved, before, bent)
        assert bent > before + 0.2, (before, bent)
        history = http.get(f"/v1/tiles/{z}/{x}/{y}/versions").json()["versions"]
        assert history[-1]["reason"] == "correction" and correction["id"] in str(history[-1]["corrections"])
        added = http.get(f"/v1/tiles/{z}/{x}/{y}/match-pairs", params={"status": "added"}).json()[
            "match_pairs"
        ]
        assert len(added) == 1 and added[0]["human"]

        undo = http.post(f"/v1/corrections/{correction['id']}/undo")
        assert undo.status_code == 202, undo.text
        assert http.post(f"/v1/corrections/{correction['id']}/undo").status_code == 409
        _settle(dep, http)
        fleet.download_results(http, ids, tmp_path / "undone", fleet.scenario_bbox(fleet_dirs["first"]))
        restored = _trip_error_m(tmp_path / "undone", fleet_dirs["first"], victim)
        assert restored <= before + 0.05, (before, bent, restored)
        history = http.get(f"/v1/tiles/{z}/{x}/{y}/versions").json()["versions"]
        assert history[-1]["reason"] == "undo correction"

        audit = http.get("/v1/corrections", params={"z": z, "x": x, "y": y}).json()["corrections"]
        (entry,) = audit
        assert entry["author_key_id"] and entry["created_at"] and entry["undone_at"] and entry["undone_by"]
        assert entry["result_version_id"] and entry["undo_version_id"] > entry["result_version_id"]
        assert entry["payload"]["offset_xyyaw"] == [0.0, 3.5, 0.0]


def test_rejecting_a_pair_reoptimizes_the_tile_and_is_audited(make_isolated, fleet_dirs, tmp_path):  # noqa: F811
    dep = make_isolated("embedded")
    dep.start_server()
    _run_fleet(dep, fleet_dirs["first"], tmp_path / "before")
    reader_key = dep.admin().post("/v1/keys", json={"role": "reader"}).json()["key"]
    z, x, y = dep.rows("SELECT z, x, y FROM tile_versions ORDER BY n_features DESC")[0]
    with dep.admin() as http:
        pairs = http.get(f"/v1/tiles/{z}/{x}/{y}/match-pairs").json()["match_pairs"]
        assert pairs and all(0 <= p["confidence"] <= 1 and p["residual_rms_m"] >= 0 for p in pairs)
        target = pairs[0]
        with dep.client(reader_key) as reader:
            assert reader.get(f"/v1/tiles/{z}/{x}/{y}/match-pairs").status_code == 200
            denied = reader.post(
                f"/v1/tiles/{z}/{x}/{y}/corrections", json={"kind": "reject_pair", "pair_id": target["id"]}
            )
            assert denied.status_code == 403
        bad = http.post(f"/v1/tiles/{z}/{x}/{y}/corrections", json={"kind": "reject_pair"})
        assert bad.status_code in (400, 422) and "pair_id" in bad.text
        missing = http.post(
            f"/v1/tiles/{z}/{x}/{y}/corrections", json={"kind": "reject_pair", "pair_id": "nope"}
        )
        assert missing.status_code == 404
        answer = http.post(
            f"/v1/tiles/{z}/{x}/{y}/corrections", json={"kind": "reject_pair", "pair_id": target["id"]}
        )
        assert answer.status_code == 202, answer.text
        again = http.post(
            f"/v1/tiles/{z}/{x}/{y}/corrections", json={"kind": "reject_pair", "pair_id": target["id"]}
        )
        assert again.status_code == 409
        _settle(dep, http)
        versions = http.get(f"/v1/tiles/{z}/{x}/{y}/versions").json()["versions"]
        assert [v["version"] for v in versions][-1] == 2 and versions[-1]["reason"] == "correction"
        rejected = http.get(f"/v1/tiles/{z}/{x}/{y}/match-pairs", params={"status": "rejected"}).json()
        assert [p["id"] for p in rejected["match_pairs"]] == [target["id"]]
        current = http.get(f"/v1/tiles/{z}/{x}/{y}/match-pairs", params={"status": "active"}).json()[
            "match_pairs"
        ]

        def overlaps(a, b):
            return a[0] <= b[1] and b[0] <= a[1]

        def same_pair(p):  # the re-alignment found no pair between the rejected frames again
            return {p["trip_i"], p["trip_j"]} == {target["trip_i"], target["trip_j"]} and any(
                overlaps(p[f"frames_{a}"], target["frames_i"])
                and overlaps(p[f"frames_{b}"], target["frames_j"])
                for a, b in (("i", "j"), ("j", "i"))
            )

        assert current and not any(same_pair(p) for p in current)
        (entry,) = http.get("/v1/corrections").json()["corrections"]
        assert entry["kind"] == "reject_pair" and entry["result_version_id"] == versions[-1]["map_version"]
