"""The map viewer in headless Chromium against the embedded deployment: the page loads, the live
vector tiles render, the version slider changes what is drawn (with the diff), an element's details,
raw vs aligned trajectories, and (once the correction endpoints exist) a correction round trip."""

from __future__ import annotations

import io
import math

import numpy as np
import pytest
from sqlalchemy.orm import Session

from services.db.models import TripPoses
from tests.browser.conftest import run_driver
from tests.browser.seed import M_PER_DEG_LAT, seed_merged_tile, seed_tile
from tests.integration.conftest import moving_trip

pytestmark = pytest.mark.integration

TILE = (16, 34875, 22744)  # holds the test drives (westwards from 48.1366, 11.5790)
CENTRE = (11.5772, 48.1366)  # of the seeded road, on the drives


def _aligned_poses(dep, trip_pk: str, doc: dict) -> None:
    """Final poses as the pipeline writes them: the raw fixes moved 1.5 m south."""
    t = np.array([f["t"] for f in doc["frames"]])
    lat = np.array([f["gnss"]["lat"] for f in doc["frames"]]) - 1.5 / M_PER_DEG_LAT
    lon = np.array([f["gnss"]["lon"] for f in doc["frames"]])
    buffer = io.BytesIO()
    np.savez_compressed(buffer, t=t, lat=lat, lon=lon, heading_deg=np.full(len(t), 270.0))
    with Session(dep.engine) as session, session.begin():
        session.merge(TripPoses(trip_pk=trip_pk, job_id="browser-test", arrays=buffer.getvalue()))


def test_viewer(browser_ready, make_isolated) -> None:
    dep = make_isolated("embedded")
    dep.start_server()
    trips = []
    for i in range(2):
        doc = moving_trip(vehicle_id=f"veh-{i}", length_m=300.0)
        trips.append((dep.upload(doc).json()["id"], doc))
    dep.wait_idle()
    _aligned_poses(dep, *trips[0])
    seed_tile(dep.db_url, *TILE, CENTRE)

    m_per_deg_lon = M_PER_DEG_LAT * math.cos(math.radians(CENTRE[1]))
    stop_line = (CENTRE[0] - 22 / m_per_deg_lon, CENTRE[1] - 3.5 / M_PER_DEG_LAT)
    result = run_driver(
        "viewer",
        base=dep.base_url,
        key=dep.admin_key,
        centre=CENTRE,
        click_lnglat=stop_line,
        tile_offset=[0.0, -0.0005],
        correct=True,
    )
    checks = result["checks"]
    assert not result["errors"], result
    assert checks["key_form_shown"]
    # the live map (version 3 of the tile) renders from the vector tiles, styled per element type
    assert checks["map_version_label"] == "map version 3"
    live = {entry.split(":")[0] for entry in checks["live_rendered"]}
    assert {
        "road_boundary",
        "centerline",
        "centerline-derived",
        "lane_divider-solid",
        "lane_divider-dashed",
        "stop_line",
        "crosswalk-fill",
    } <= live, checks["live_rendered"]
    assert "road_marking-fill" not in live  # removed in version 3
    assert checks["live_drawn_share"] > 0.005
    # clicking selects the tile; the slider walks its versions, oldest drawn last
    assert checks["tile_name"] == "/".join(map(str, TILE))
    by_version = {v["index"] + 1: v for v in checks["versions"]}
    assert set(by_version) == {1, 2, 3}
    ids = {n: {d.split(":")[1] for d in v["drawn"]} for n, v in by_version.items()}
    assert "rm-arrow" in ids[1] and "sl-1" not in ids[1]
    assert {"rm-arrow", "sl-1"} <= ids[2]
    assert "sl-1" in ids[3] and "rm-arrow" not in ids[3]
    assert sorted(by_version[2]["diff"]) == ["added:sl-1", "modified:ld-centre"]
    assert by_version[3]["diff"] == ["removed:rm-arrow"]
    assert by_version[2]["label"].startswith("v2 of 3") and "+1 ~1 −0" in by_version[2]["label"]
    # validator flags are drawn by level (the TileJSON's flag_levels): a feature shows its most
    # severe flag, only severe ones glow strongly; the legend names the three levels
    assert checks["flagged"] == ["flags:cl-west", "flags:ld-north", "flags:rb-north", "flags:rb-south"]
    styles = checks["flag_styles"]
    severe, warning, info = styles["rb-north"], styles["ld-north"], styles["cl-west"]
    assert styles["rb-south"] == {**severe, "flags": styles["rb-south"]["flags"]}  # gap among them: severe
    assert len({s["color"] for s in (severe, warning, info)}) == 3
    assert severe["width"] > warning["width"] > info["width"]
    assert severe["opacity"] > warning["opacity"] > info["opacity"]
    assert severe["blur"] > warning["blur"] >= info["blur"]
    for level in ("severe", "warning", "informative"):
        assert f"validator flag: {level}" in checks["legend"]
    # an element's details come from /v1/features/{id}
    text = checks["element_text"]
    assert "sl-1" in text and "stop_line" in text and "4 trips, 120 observations" in text
    assert "0.050 m" in text and "v2 added" in text and "v3 unchanged" in text
    # trips in view, raw and aligned
    assert checks["trips_listed"] == 2
    tracks = {entry.split(":")[0] for entry in checks["tracks_rendered"]}
    assert tracks == {"raw", "aligned"}, checks["tracks_rendered"]
    # corrections: the panel shows when the tile's match pairs can be listed (see docs/viewer.md)
    assert "corrections_visible" in checks

    # where the viewer opens: on the data without a hash or with one elsewhere (Berlin); on a shared
    # link that shows the data, on that view
    link = f"#18/{CENTRE[1]}/{CENTRE[0]}"
    opened = run_driver("open", base=dep.base_url, key=dep.admin_key, hashes=["", "#16/52.52/13.405", link])
    assert not opened["errors"], opened
    no_hash, elsewhere, shared = opened["checks"]["opened"]
    with dep.admin() as http:
        west, south, east, north = http.get("/v1/tiles.json").json()["bounds"]
    for seen in (no_hash, elsewhere):
        assert seen["opened_on"] == "data", seen
        w, s, e, n = seen["view"]  # the whole of the data in view
        assert w <= west and s <= south and e >= east and n >= north, (seen, (west, south, east, north))
        assert seen["rendered"] >= 8 and seen["drawn_share"] > 0.003, seen
        assert seen["hash_after"] != seen["hash"]
    assert shared["opened_on"] == "link" and shared["hash_after"].startswith("#18/"), shared
    assert shared["zoom"] == 18 and shared["rendered"] >= 8, shared


def test_viewer_held_back_lines(browser_ready, make_isolated) -> None:
    """The tile panel's "held-back lines" toggle against ``GET /v1/tiles/{z}/{x}/{y}/held-back``: a
    version the real merge job made with two ghosts held back (drawn, counted, clickable), one it made
    with none ("none held back"), and a version written without a topology state (the API's 409)."""
    dep = make_isolated("embedded")
    dep.start_server()
    z, x, y = TILE
    clean, ghosts = (z, x - 1, y), (z, x + 1, y)  # the seeded road's tile between them
    north = 25 / M_PER_DEG_LAT  # click 25 m north of a merged road: on no line
    clicks = {
        clean: seed_merged_tile(dep.db_url, *clean, ghosts=False),
        ghosts: seed_merged_tile(dep.db_url, *ghosts, ghosts=True),
    }
    clicks = {t: (lon, lat + north) for t, (lon, lat) in clicks.items()}
    seed_tile(dep.db_url, *TILE, CENTRE)  # three versions written without a topology state
    clicks[TILE] = (CENTRE[0], CENTRE[1] - 0.0005)
    names = {t: "/".join(map(str, t)) for t in (clean, ghosts, TILE)}
    with dep.admin() as http:
        api = {t: http.get(f"/v1/tiles/{name}/held-back") for t, name in names.items()}
    assert api[clean].status_code == 200 and api[clean].json()["features"] == []
    held = api[ghosts].json()
    assert api[ghosts].status_code == 200 and len(held["features"]) == 2, held  # a divider and a boundary
    assert api[TILE].status_code == 409 and api[TILE].json()["error"] == "state_unavailable"

    result = run_driver(
        "held-back",
        base=dep.base_url,
        key=dep.admin_key,
        tiles=[{"name": names[t], "click": clicks[t]} for t in (clean, ghosts, TILE)],
    )
    assert not result["errors"], result
    seen = {name: result["checks"]["tiles"][name] for name in names.values()}
    first = seen[names[clean]]
    assert first["off"] == {"text": "", "rendered": [], "source": None}  # off: nothing asked, nothing drawn
    assert first["tile_name"] == names[clean]
    # on: the version the slider shows, none held back from it
    assert first["on"]["path"] == f"/v1/tiles/{names[clean]}/held-back?version=1"
    assert first["on"]["status"] == 200
    assert (first["on"]["text"], first["on"]["rendered"], first["on"]["source"]) == ("none held back", [], 0)
    # two held back: drawn on their own layer, counted, as the API answers
    ghost = seen[names[ghosts]]
    ids = sorted(f["id"] for f in held["features"])
    assert ghost["on"]["path"] == f"/v1/tiles/{names[ghosts]}/held-back?version=1"
    assert ghost["on"]["status"] == 200
    assert ghost["on"]["text"] == f"{len(ids)} held back"
    assert ghost["on"]["rendered"] == ids and ghost["on"]["source"] == len(ids)
    # a held-back line's details: its own properties (it is in no version)
    clicked = next(f for f in held["features"] if f["id"] == ghost["clicked_id"])
    text = ghost["element_text"]
    assert ghost["clicked_id"] in text and clicked["properties"]["type"] in text
    passed = clicked["properties"]["passed_trips"]
    assert f"held back: {passed} trips drove alongside without seeing it" in text
    # the live map: the tile's latest version, without ?version
    assert ghost["live"]["path"] == f"/v1/tiles/{names[ghosts]}/held-back"
    assert (ghost["live"]["text"], ghost["live"]["rendered"]) == (f"{len(ids)} held back", ids)
    # no readable state: the API's message, not "none held back"
    unknown = seen[names[TILE]]
    assert unknown["on"]["path"] == f"/v1/tiles/{names[TILE]}/held-back?version=3"
    assert unknown["on"]["status"] == 409
    assert unknown["on"]["text"] == f"unknown: {api[TILE].json()['message']}"
    assert unknown["on"]["rendered"] == [] and unknown["on"]["source"] is None
    assert unknown["version_label"].startswith("v3 of 3")
    # off again: nothing drawn
    assert result["checks"]["off_again"] == {"text": "", "rendered": [], "source": None}


ADD_OFFSET = [0.1, -0.05, 0.002]  # metres, metres, radians: asserted with the added pair


def test_viewer_on_the_pipeline(browser_ready, make_isolated) -> None:
    """A small fleet through the real pipeline (ingest, align_tile, merge_tile) in two batches: two
    versions of the tile, real aligned poses, real match pairs; a correction round trip through the
    page once the correction endpoints exist: reject a pair, undo it, then add a pair through the
    form (prefilled from a listed pair, with an asserted offset)."""
    dep = make_isolated("embedded")
    dep.start_server()
    with dep.admin() as http:
        for _batch in range(2):
            for i in range(3):
                assert dep.upload(moving_trip(vehicle_id=f"veh-{i}", length_m=300.0)).status_code == 202
            dep.wait_idle()
            assert http.post("/v1/process").json()["scheduled"] >= 1
            dep.wait_idle()
        assert dep.summary()["failed"] == 0
        tile = "/".join(map(str, TILE))
        versions = http.get(f"/v1/tiles/{tile}/versions").raise_for_status().json()["versions"]
        assert len(versions) == 2
        pairs = http.get(f"/v1/tiles/{tile}/match-pairs")
    corrections_exist = pairs.status_code == 200

    result = run_driver(
        "viewer",
        base=dep.base_url,
        key=dep.admin_key,
        centre=(11.5775, 48.1366),
        correct=corrections_exist,
        add_offset=ADD_OFFSET,
        out_prefix="pipeline-",
    )
    checks = result["checks"]
    assert not result["errors"], result
    assert len(checks["live_rendered"]) >= 3 and checks["live_drawn_share"] > 0.003
    by_version = {v["index"] + 1: v for v in checks["versions"]}
    assert set(by_version) == {1, 2} and by_version[1]["drawn"] and by_version[2]["drawn"]
    assert by_version[1]["diff"] and all(d.startswith("added:") for d in by_version[1]["diff"])
    assert "history" in checks["element_text"].lower()
    assert checks["trips_listed"] == 6
    assert {entry.split(":")[0] for entry in checks["tracks_rendered"]} == {"raw", "aligned"}
    if corrections_exist:  # the human-correction round trip (admin): reject a pair, then undo it
        assert checks["corrections_visible"] and checks["pairs_listed"] >= 1
        assert checks["corrections_listed"] == 1, checks
        assert checks["correction_message"].startswith("reject_pair: job done, map version"), checks
        assert checks["pair_status_after"] == "rejected"
        assert checks["versions_after_correction"] == 1
        assert "reject_pair" in checks["correction_row"] and "→ map v" in checks["correction_row"]
        assert checks["undo_message"].startswith("undo: job done, map version"), checks
        assert checks["versions_after_undo"] == 1
        assert "undone → map v" in checks["correction_row_after_undo"]
        # add a pair through the form: prefilled from the clicked pair; a bad frame gets the API's 422
        source = checks["add_from_pair"]
        sides = ("trip_i", "trip_j", "frames_i", "frames_j")
        assert checks["add_prefilled"] == {k: source[k] for k in sides}
        assert checks["add_trip_options"] >= 2  # "the map" and the trips crossing the tile
        assert (
            checks["add_error_message"].startswith("frames_i: ") and "999999" in checks["add_error_message"]
        )
        assert checks["add_error_marked"] == 2
        assert checks["add_message"].startswith("add_pair: job done, map version"), checks
        assert (
            checks["add_version_label"].startswith("v5 of 5")
            and " · correction · " in checks["add_version_label"]
        )
        assert len(checks["add_correction_rows"]) == 2 and "add_pair" in checks["add_correction_rows"][1]
        assert "→ map v" in checks["add_correction_rows"][1]
        trips = {source["trip_i"], source["trip_j"]}
        added = [r for r in checks["add_pair_rows"] if r["status"] == "added human"]
        assert any(set(r["trips"].split(" ↔ ")) == trips for r in added), checks["add_pair_rows"]
        with dep.admin() as http:
            rejected, added_c = http.get(
                "/v1/corrections", params={"z": TILE[0], "x": TILE[1], "y": TILE[2]}
            ).json()["corrections"]
            assert rejected["payload"]["pair_id"] == checks["rejected_pair"]
            assert rejected["result_version_id"] and rejected["undo_version_id"] and rejected["undone_at"]
            assert added_c["kind"] == "add_pair" and added_c["result_version_id"] and not added_c["undone_at"]
            assert {k: added_c["payload"][k] for k in sides} == {k: source[k] for k in sides}
            assert added_c["payload"]["offset_xyyaw"] == ADD_OFFSET
            assert added_c["payload"]["note"].startswith("browser test")
            # the 202 answer shown by the form names the correction and its job
            assert (
                checks["add_answer_message"] == f"correction {added_c['id']} queued: job {added_c['job_id']}"
            )
            reasons = [v["reason"] for v in http.get(f"/v1/tiles/{tile}/versions").json()["versions"]]
            assert reasons == ["merge", "merge", "correction", "undo correction", "correction"], reasons
            pairs = http.get(f"/v1/tiles/{tile}/match-pairs").json()["match_pairs"]
            assert any(
                p["human"] and p["status"] == "added" and {p["trip_i"], p["trip_j"]} == trips for p in pairs
            )
    else:
        assert checks["corrections_visible"] is False
