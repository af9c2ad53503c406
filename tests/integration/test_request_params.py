"""Path and query parameters no database can look up answer 422 naming the parameter, the same on
both deployments (an integer past the 32-bit columns, a tile outside its zoom, a NUL byte)."""

from __future__ import annotations

import base64

import orjson
import pytest

from tests.integration.conftest import Deployment

pytestmark = pytest.mark.integration

# (method, URL, location)
OUT_OF_RANGE = [
    ("GET", "/v1/changes?since=2147483648", "query.since"),
    ("GET", "/v1/changes?since=9223372036854775808", "query.since"),
    ("GET", "/v1/corrections?z=2147483648&x=0&y=0", "query.z"),
    ("GET", "/v1/tiles/0/2147483648/0/match-pairs", "path.x"),
    ("GET", "/v1/tiles/0/0/0/versions/2147483648", "path.v"),
    ("GET", "/v1/tiles/0/0/0/diff?from=1&to=9223372036854775808", "query.to"),
    ("GET", "/v1/map?bbox=8.4,49.0,8.41,49.01&version=2147483648", "query.version"),
    ("GET", "/v1/tiles/0/1/0/versions", "path.x"),
    ("GET", "/v1/tiles/3/0/8/match-pairs", "path.y"),
    ("GET", "/v1/tiles/0/0/2147483648.mvt", "path.y"),
]
NUL = [
    ("GET", "/v1/trips/%00", "path.trip_pk"),
    ("GET", "/v1/trips/%00/poses", "path.trip_pk"),
    ("GET", "/v1/trips/%00/track.geojson", "path.trip_pk"),
    ("GET", "/v1/jobs/%00", "path.job_id"),
    ("GET", "/v1/features/%00", "path.feature_id"),
    ("GET", "/v1/jobs?subject=%00", "query.subject"),
    ("DELETE", "/v1/keys/%00", "path.key_id"),
    ("POST", "/v1/jobs/%00/retry", "path.job_id"),
    ("POST", "/v1/corrections/a%00b/undo", "path.correction_id"),
]


def cursor(key: list) -> str:
    return base64.urlsafe_b64encode(orjson.dumps(key)).decode().rstrip("=")


# (method, URL, JSON body, location): the same rules inside cursors and request bodies
INSIDE = [
    ("GET", f"/v1/tiles/16/1/1/match-pairs?cursor={cursor([0.5, chr(0)])}", None, "query.cursor"),
    ("GET", f"/v1/tiles/16/1/1/match-pairs?cursor={cursor([0.5, 2**40])}", None, "query.cursor"),
    ("POST", "/v1/tiles/16/1/1/corrections", {"kind": "reject_pair", "pair_id": "a\u0000b"}, "body.pair_id"),
    (
        "POST",
        "/v1/tiles/16/1/1/corrections",
        {"kind": "add_pair", "trip_i": "a\u0000", "frames_i": [0, 1], "frames_j": [0, 1]},
        "body.trip_i",
    ),
    (
        "POST",
        "/v1/tiles/16/1/1/corrections",
        {"kind": "reject_pair", "pair_id": "p", "note": "\u0000"},
        "body.note",
    ),
    ("POST", "/v1/tiles/16/1/1/rollback", {"version": 2**40}, "body.version"),
    ("POST", "/v1/tiles/16/1/1/versions/1/approve", {"expected_latest": 2**40}, "body.expected_latest"),
]


@pytest.mark.parametrize("method,url,body,location", INSIDE, ids=[c[3] + "-" + c[1][:40] for c in INSIDE])
def test_cursors_and_bodies_follow_the_same_rules(
    deployment: Deployment, method: str, url: str, body: dict | None, location: str
) -> None:
    with deployment.admin() as http:
        response = http.request(method, url, json=body)
    assert response.status_code == 422, response.text
    assert response.json()["location"] == location


@pytest.mark.parametrize("method,url,location", OUT_OF_RANGE + NUL, ids=[c[1] for c in OUT_OF_RANGE + NUL])
def test_a_parameter_no_database_can_look_up_is_422_naming_it(
    deployment: Deployment, method: str, url: str, location: str
) -> None:
    with deployment.admin() as http:
        response = http.request(method, url)
    assert response.status_code == 422, response.text
    body = response.json()
    assert set(body) == {"error", "location", "message"}
    assert (body["error"], body["location"]) == ("invalid_request", location)


def test_well_formed_unknown_ids_are_still_404(deployment: Deployment) -> None:
    with deployment.admin() as http:
        for url in ("/v1/trips/nope", "/v1/jobs/nope", "/v1/tiles/0/0/0/versions/2147483647"):
            assert http.get(url).status_code == 404, url
