"""The version store (``services.db.versions``) and its HTTP side on both deployments: change types,
history, diff, the changes feed, rollback, approval of a candidate, the expected-version check
(OSM API's 409) and two concurrent writers of one tile, the feature history, write roles."""

from __future__ import annotations

import threading
import time
from collections.abc import Iterator

import mercantile
import pytest
from shapely.geometry import shape

from services.db import versions as vs
from services.db.models import MapFeatureRow, TileHead, TileVersion
from services.db.repo import BOOTSTRAP_ADMIN_ID
from tests.integration.conftest import PgDatabases
from tests.integration.test_tiles import Tiled, decode, frac, road, start_tiled

pytestmark = pytest.mark.integration


@pytest.fixture(scope="module", params=["embedded", "distributed"])
def tiled(request, tmp_path_factory, pg: PgDatabases, shared_redis_url: str) -> Iterator[Tiled]:
    yield from start_tiled(
        request.param, tmp_path_factory.mktemp(f"versions-{request.param}"), pg, shared_redis_url
    )


def _moved(f: vs.VersionFeature, north_m: float) -> vs.VersionFeature:
    from shapely import affinity

    return vs.VersionFeature(
        f.feature_id, f.type, f.style, f.properties, affinity.translate(f.geometry, yoff=north_m / 111_320.0)
    )


def _features(tiled: Tiled, tile_version_id: int, include_removed: bool = False) -> list[vs.VersionFeature]:
    with tiled.sessions() as session:
        return vs.version_features(session, tile_version_id=tile_version_id, include_removed=include_removed)


def _counts(tiled: Tiled) -> tuple[int, int]:
    with tiled.sessions() as session:
        return session.query(TileVersion).count(), session.query(MapFeatureRow).count()


def test_change_types_history_and_version_geojson(tiled: Tiled):
    tile = tiled.fresh_tile()
    b1, d1, c1, x1 = road(tile)
    first = tiled.write(tile, [b1, d1, c1, x1])
    assert (first.version, first.status, first.parent_version) == (1, "published", None)
    assert first.changes == {"added": 4, "modified": 0, "unchanged": 0, "removed": 0}
    d1_solid = vs.VersionFeature(d1.feature_id, d1.type, "solid", d1.properties, d1.geometry)
    new = vs.VersionFeature(
        f"t{tile.x}-s1",
        "stop_line",
        None,
        {"support": 2},
        shape({"type": "LineString", "coordinates": [frac(tile, 0.6, 0.6), frac(tile, 0.7, 0.6)]}),
    )
    second = tiled.write(
        tile,
        [_moved(b1, 0.0002), _moved(c1, 0.5), d1_solid, new],  # 0.2 mm: unchanged; 0.5 m: modified
        reason="merge",
        job_id="job-2",
        trips=["trip-b"],
    )
    assert second.version == 2 and second.parent_version == 1
    assert second.changes == {"added": 1, "modified": 2, "unchanged": 1, "removed": 1}
    rows = {f.feature_id: f for f in _features(tiled, second.id, include_removed=True)}
    assert set(rows) == {b1.feature_id, d1.feature_id, c1.feature_id, x1.feature_id, new.feature_id}
    assert rows[x1.feature_id].geometry.equals_exact(x1.geometry, 1e-7)  # removed keeps its last geometry
    assert x1.feature_id not in {f.feature_id for f in _features(tiled, second.id)}

    with tiled.http() as http:
        history = http.get(f"/v1/tiles/{tile.z}/{tile.x}/{tile.y}/versions").raise_for_status().json()
        assert (history["latest_version"], history["live_version"]) == (2, 2)
        assert [v["version"] for v in history["versions"]] == [1, 2]
        v2 = history["versions"][1]
        assert v2["job_id"] == "job-2" and v2["trips"] == ["trip-b"] and v2["reason"] == "merge"
        assert (
            v2["changes"]["removed"] == 1
            and v2["map_version"] == second.id
            and v2["created_at"].endswith("+00:00")
        )
        assert v2["quality"] == {"ok": True} and v2["status"] == "published"
        gj = http.get(
            f"/v1/tiles/{tile.z}/{tile.x}/{tile.y}/versions/2", params={"include_removed": True}
        ).json()
        changes = {f["id"]: f["properties"]["change"] for f in gj["features"]}
        assert changes == {
            b1.feature_id: "unchanged",
            c1.feature_id: "modified",
            d1.feature_id: "modified",
            new.feature_id: "added",
            x1.feature_id: "removed",
        }
        assert len(http.get(f"/v1/tiles/{tile.z}/{tile.x}/{tile.y}/versions/1").json()["features"]) == 4
        assert http.get(f"/v1/tiles/{tile.z}/{tile.x}/{tile.y}/versions/9").status_code == 404
        assert http.get("/v1/tiles/16/1/1/versions").status_code == 404

        diff = http.get(f"/v1/tiles/{tile.z}/{tile.x}/{tile.y}/diff", params={"from": 1, "to": 2}).json()
        assert [f["id"] for f in diff["added"]] == [new.feature_id]
        assert [f["id"] for f in diff["removed"]] == [x1.feature_id]
        assert diff["removed"][0]["geometry"]["type"] == "Polygon"
        assert sorted(m["id"] for m in diff["modified"]) == sorted([c1.feature_id, d1.feature_id])
        assert diff["unchanged"] == 1
        moved = next(m for m in diff["modified"] if m["id"] == c1.feature_id)
        dy_deg = (
            moved["after"]["geometry"]["coordinates"][0][1] - moved["before"]["geometry"]["coordinates"][0][1]
        )
        assert dy_deg * 111_320 == pytest.approx(0.5, abs=0.01)
        assert (
            http.get(f"/v1/tiles/{tile.z}/{tile.x}/{tile.y}/diff", params={"from": 1, "to": 7}).status_code
            == 404
        )

        feature = http.get(f"/v1/features/{c1.feature_id}").raise_for_status().json()
        assert feature["properties"]["live"] is True and feature["properties"]["tile_version"] == 2
        assert [(h["version"], h["change"]) for h in feature["history"]] == [(1, "added"), (2, "modified")]
        gone = http.get(f"/v1/features/{x1.feature_id}").json()
        assert gone["properties"]["live"] is False and gone["properties"]["change"] == "removed"
        assert http.get("/v1/features/no-such-feature").status_code == 404


def test_changes_feed_pages_in_map_version_order(tiled: Tiled):
    start = tiled.map_version()
    tiles = [tiled.fresh_tile(), tiled.fresh_tile()]
    made = [
        tiled.write(tiles[0], road(tiles[0])),
        tiled.write(tiles[1], road(tiles[1])),
        tiled.write(tiles[0], road(tiles[0])[:2]),
    ]
    with tiled.http() as http:
        feed = http.get("/v1/changes", params={"since": start}).raise_for_status().json()
        assert [c["map_version"] for c in feed["changes"]] == [v.id for v in made]
        assert feed["next"] == made[-1].id == feed["map_version"] and feed["more"] is False
        last = feed["changes"][-1]
        assert last["tile"] == f"16/{tiles[0].x}/{tiles[0].y}" and last["version"] == 2
        assert sorted(f["change"] for f in last["features"]) == [
            "removed",
            "removed",
        ]  # unchanged ones omitted
        page, cursor, seen = None, start, []
        while page is None or page["more"]:
            page = http.get("/v1/changes", params={"since": cursor, "limit": 1}).json()
            seen += [c["map_version"] for c in page["changes"]]
            cursor = page["next"]
        assert seen == [v.id for v in made]
        assert http.get("/v1/changes", params={"since": cursor}).json()["changes"] == []
        assert http.get("/v1/changes", params={"limit": 0}).status_code == 422


def test_rollback_publishes_the_old_version_again(tiled: Tiled):
    tile = tiled.fresh_tile()
    first = tiled.write(tile, road(tile))
    tiled.write(tile, road(tile, shift=0.1)[:2], state=b"state-2")
    url = f"/v1/tiles/{tile.z}/{tile.x}/{tile.y}"
    with tiled.http(tiled.dep.admin_key) as admin, tiled.http() as reader:
        before = reader.get(url + ".mvt")
        assert reader.post(url + "/rollback", json={"version": 1}).status_code == 403
        stale = admin.post(url + "/rollback", json={"version": 1, "expected_latest": 1})
        assert stale.status_code == 409 and stale.json()["error"] == "conflict"
        assert admin.post(url + "/rollback", json={"version": 5}).status_code == 404
        response = admin.post(url + "/rollback", json={"version": 1, "expected_latest": 2})
        assert response.status_code == 201, response.text
        body = response.json()
        assert (body["version"], body["reason"], body["status"]) == (3, "rollback to v1", "published")
        assert body["quality"]["review"] == {"action": "rollback", "by": BOOTSTRAP_ADMIN_ID, "of_version": 1}
        assert response.headers["location"] == f"{url}/versions/3"
        after = reader.get(url + ".mvt")
        assert after.headers["etag"] != before.headers["etag"]
        assert set(decode(after.content)) == {f.feature_id for f in road(tile)}
    with tiled.sessions() as session:
        third = vs.get_version(session, z=tile.z, x=tile.x, y=tile.y, version=3)
        assert third is not None
        assert third.state == first.state == b"state" and third.trips == first.trips
    old, new = _features(tiled, first.id), _features(tiled, third.id)
    assert [(f.feature_id, f.type, f.style, f.properties) for f in old] == [
        (f.feature_id, f.type, f.style, f.properties) for f in new
    ]
    assert all(a.geometry.equals_exact(b.geometry, 1e-9) for a, b in zip(old, new, strict=True))


def test_a_candidate_is_not_live_until_approved(tiled: Tiled):
    tile = tiled.fresh_tile()
    tiled.write(tile, road(tile))
    live_before = tiled.map_version()
    candidate = tiled.write(tile, road(tile, shift=0.2), publish=False, reason="merge")
    assert candidate.status == "candidate"
    url = f"/v1/tiles/{tile.z}/{tile.x}/{tile.y}"
    w, s, e, n = mercantile.bounds(tile)
    with tiled.http(tiled.dep.admin_key) as admin, tiled.http() as reader:
        live = reader.get("/v1/map", params={"bbox": f"{w},{s},{e},{n}"}).json()
        boundary = next(f for f in live["features"] if f["id"].endswith("-b1"))
        assert shape(boundary["geometry"]).equals_exact(road(tile)[0].geometry, 1e-7)  # still v1
        history = reader.get(url + "/versions").json()
        assert (history["latest_version"], history["live_version"]) == (2, 1)
        assert reader.post(url + "/versions/2/approve").status_code == 403
        assert admin.post(url + "/versions/1/approve").status_code == 409  # not a candidate
        approved = admin.post(url + "/versions/2/approve")
        assert approved.status_code == 201, approved.text
        assert (approved.json()["version"], approved.json()["status"], approved.json()["reason"]) == (
            3,
            "approved",
            "approve v2",
        )
        live = reader.get("/v1/map", params={"bbox": f"{w},{s},{e},{n}"}).json()
        boundary = next(f for f in live["features"] if f["id"].endswith("-b1"))
        assert shape(boundary["geometry"]).equals_exact(road(tile, shift=0.2)[0].geometry, 1e-7)
        # the map as it was stays as it was
        pinned = reader.get("/v1/map", params={"bbox": f"{w},{s},{e},{n}", "version": candidate.id}).json()
        boundary = next(f for f in pinned["features"] if f["id"].endswith("-b1"))
        assert shape(boundary["geometry"]).equals_exact(road(tile)[0].geometry, 1e-7)
        assert live_before < candidate.id
        again = admin.post(url + "/versions/2/approve", json={"expected_latest": 2})
        assert again.status_code == 409 and again.json()["error"] == "conflict"  # latest is 3 now


def test_a_stale_expected_version_is_a_conflict_and_writes_nothing(tiled: Tiled):
    tile = tiled.fresh_tile()
    tiled.write(tile, road(tile))
    counts = _counts(tiled)
    for stale in (None, 0, 2):
        with pytest.raises(vs.VersionConflict) as err:
            tiled.write(tile, road(tile, shift=0.1), expected_latest=stale)
        assert err.value.latest == 1 and err.value.expected == stale
    assert _counts(tiled) == counts
    with tiled.sessions() as session:
        head = vs.tile_head(session, z=tile.z, x=tile.x, y=tile.y)
        assert head is not None and head.latest_version == 1


def test_two_concurrent_writers_one_wins_the_other_conflicts(tiled: Tiled):
    """Two sessions write the same tile with the same expected version at the same time: the
    second waits for the first (advisory lock on PostgreSQL, the write lock on SQLite), then sees
    the new version and gets VersionConflict; nothing of it is written."""
    tile = tiled.fresh_tile()
    tiled.write(tile, road(tile))
    counts = _counts(tiled)
    first_written, release = threading.Event(), threading.Event()
    results: dict[str, object] = {}
    finished_at: dict[str, float] = {}

    def writer(name: str, features, hold: bool) -> None:
        try:
            with tiled.sessions.begin() as session:
                version = vs.write_tile_version(
                    session,
                    z=tile.z,
                    x=tile.x,
                    y=tile.y,
                    features=features,
                    reason="merge",
                    job_id=name,
                    trips=[name],
                    corrections=[],
                    quality={},
                    origin_lat=49.0,
                    origin_lon=8.4,
                    state=None,
                    publish=True,
                    expected_latest=1,
                )
                results[name] = version.version
                if hold:
                    first_written.set()
                    release.wait(30)
        except vs.VersionConflict as exc:
            results[name] = exc
        finally:
            finished_at[name] = time.monotonic()

    a = threading.Thread(target=writer, args=("job-a", road(tile, shift=0.1), True))
    a.start()
    assert first_written.wait(30)
    b = threading.Thread(target=writer, args=("job-b", road(tile, shift=0.2), False))
    b.start()
    time.sleep(1.0)
    assert b.is_alive(), "the second writer did not wait for the first"
    released_at = time.monotonic()
    release.set()
    a.join(30)
    b.join(60)
    assert results["job-a"] == 2
    assert isinstance(results["job-b"], vs.VersionConflict) and results["job-b"].latest == 2
    assert finished_at["job-b"] >= released_at
    versions_before, rows_before = counts
    assert _counts(tiled) == (versions_before + 1, rows_before + 4)
    with tiled.sessions() as session:
        head = session.get(TileHead, (tile.z, tile.x, tile.y))
        assert head is not None and (head.latest_version, head.live_version) == (2, 2)
        latest = vs.latest_version(session, z=tile.z, x=tile.x, y=tile.y)
        assert latest is not None and latest.job_id == "job-a" and latest.trips == ["job-a"]
