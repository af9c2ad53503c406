"""Trip geometry for the viewer on both deployments: ``GET /v1/trips?bbox=`` and
``GET /v1/trips/{id}/track.geojson`` (raw GNSS track; the aligned trajectory once final poses exist)."""

from __future__ import annotations

import io

import numpy as np
import pytest
from sqlalchemy.orm import Session

from services.db.models import TripPoses
from tests.integration.conftest import Deployment, moving_trip

pytestmark = pytest.mark.integration


@pytest.fixture(scope="module")
def trip(deployment: Deployment) -> dict:
    """An ingested 150 m westward drive and its upload."""
    doc = moving_trip(vehicle_id="veh-geom")
    response = deployment.upload(doc)
    assert response.status_code == 202, response.text
    deployment.wait_idle()
    return {"pk": response.json()["id"], "doc": doc}


def _keys(dep: Deployment) -> dict[str, str]:
    with dep.admin() as http:
        return {
            role: http.post("/v1/keys", json=body).raise_for_status().json()["key"]
            for role, body in {
                "reader": {"role": "reader"},
                "vehicle": {"role": "vehicle", "vehicle_id": "veh-geom"},
                "other": {"role": "vehicle", "vehicle_id": "veh-other"},
            }.items()
        }


def _fixes(doc: dict) -> np.ndarray:
    return np.array([[f["gnss"]["lon"], f["gnss"]["lat"]] for f in doc["frames"] if f.get("gnss")])


def test_trips_in_bbox(deployment: Deployment, trip: dict) -> None:
    keys = _keys(deployment)
    lonlat = _fixes(trip["doc"])
    (west, south), (east, north) = lonlat.min(axis=0), lonlat.max(axis=0)
    with deployment.client(keys["reader"]) as http:

        def ids(bbox: str, **params) -> list[str]:
            response = http.get("/v1/trips", params={"bbox": bbox, **params})
            assert response.status_code == 200, response.text
            return [t["id"] for t in response.json()["trips"]]

        around = f"{west - 1e-4},{south - 1e-4},{east + 1e-4},{north + 1e-4}"
        assert trip["pk"] in ids(around)
        listed = http.get("/v1/trips", params={"bbox": around}).json()["trips"]
        mine = next(t for t in listed if t["id"] == trip["pk"])
        assert mine["vehicle_id"] == "veh-geom" and mine["status"] in ("processing", "aligned")
        assert mine["length_km"] == pytest.approx(0.15, rel=0.05)
        # a box on the track's middle part only, and one beside it
        mid = (west + east) / 2
        assert trip["pk"] in ids(f"{mid - 1e-5},{south - 1e-4},{mid + 1e-5},{north + 1e-4}")
        assert trip["pk"] not in ids(f"{west - 1e-4},{north + 5e-4},{east + 1e-4},{north + 9e-4}")
        assert trip["pk"] not in ids("-1,-1,1,1")
        # limit and truncation
        one = http.get("/v1/trips", params={"bbox": around, "limit": 1}).json()
        assert len(one["trips"]) == 1
        for bad in ("1,2,3", "a,b,c,d", "2,0,1,1", "0,0,1,nan"):
            answer = http.get("/v1/trips", params={"bbox": bad})
            assert answer.status_code == 422 and answer.json()["location"] == "bbox", bad
        assert http.get("/v1/trips").status_code == 422
    with deployment.client(keys["vehicle"]) as vehicle:  # a vehicle lists its own trips only
        own = vehicle.get("/v1/trips", params={"bbox": around})
        assert own.status_code == 200, own.text
        assert trip["pk"] in [t["id"] for t in own.json()["trips"]]
        assert {t["vehicle_id"] for t in own.json()["trips"]} == {"veh-geom"}
    with deployment.client(keys["other"]) as other:
        listed = other.get("/v1/trips", params={"bbox": around})
        assert listed.status_code == 200, listed.text
        assert all(t["vehicle_id"] == "veh-other" for t in listed.json()["trips"])


def test_track_geojson_raw_then_aligned(deployment: Deployment, trip: dict) -> None:
    keys = _keys(deployment)
    lonlat = _fixes(trip["doc"])
    with Session(deployment.engine) as session, session.begin():  # no alignment yet in this test
        session.query(TripPoses).filter(TripPoses.trip_pk == trip["pk"]).delete()
    with deployment.client(keys["reader"]) as http:
        response = http.get(f"/v1/trips/{trip['pk']}/track.geojson")
        assert response.status_code == 200, response.text
        assert response.headers["content-type"] == "application/geo+json"
        doc = response.json()
        assert doc["type"] == "FeatureCollection" and doc["trip"]["id"] == trip["pk"]
        assert [f["properties"]["kind"] for f in doc["features"]] == ["raw"]
        raw = doc["features"][0]
        assert raw["geometry"]["type"] == "LineString"
        coords = np.array(raw["geometry"]["coordinates"])
        np.testing.assert_allclose(coords[0], lonlat[0], atol=1e-7)
        np.testing.assert_allclose(coords[-1], lonlat[-1], atol=1e-7)
        assert http.get("/v1/trips/no-such-trip/track.geojson").status_code == 404

    # final poses (as the tile pipeline writes them): the aligned trajectory appears
    n = len(trip["doc"]["frames"])
    t = np.array([f["t"] for f in trip["doc"]["frames"]])
    lat = np.full(n, np.nan)
    lon = np.full(n, np.nan)
    lat[1:], lon[1:] = lonlat[1:n, 1] + 1e-6, lonlat[1:n, 0] - 1e-6  # frame 0 without a pose
    buffer = io.BytesIO()
    np.savez_compressed(buffer, t=t, lat=lat, lon=lon, heading_deg=np.full(n, 270.0))
    with Session(deployment.engine) as session, session.begin():
        session.merge(TripPoses(trip_pk=trip["pk"], job_id="test-job", arrays=buffer.getvalue()))
    with deployment.client(keys["vehicle"]) as own:  # a vehicle reads its own trip's track
        doc = own.get(f"/v1/trips/{trip['pk']}/track.geojson").json()
    kinds = {f["properties"]["kind"]: f for f in doc["features"]}
    assert set(kinds) == {"raw", "aligned"}
    aligned = kinds["aligned"]
    assert aligned["properties"]["n_points"] == n - 1 and aligned["properties"]["job_id"] == "test-job"
    # GeoJSON coordinates are sent to 7 decimals
    np.testing.assert_allclose(aligned["geometry"]["coordinates"][0], [lon[1], lat[1]], atol=0.5e-7 + 1e-12)
    assert doc["bbox"] == [
        min(c[i] for f in doc["features"] for c in f["geometry"]["coordinates"]) for i in (0, 1)
    ] + [max(c[i] for f in doc["features"] for c in f["geometry"]["coordinates"]) for i in (0, 1)]
    assert aligned["properties"]["t_start"] == pytest.approx(t[1])
    with deployment.client(keys["other"]) as other:
        assert other.get(f"/v1/trips/{trip['pk']}/track.geojson").status_code == 403
    with Session(deployment.engine) as session, session.begin():
        session.query(TripPoses).filter(TripPoses.trip_pk == trip["pk"]).delete()
