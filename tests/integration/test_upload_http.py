"""Contract section 1 through HTTP, on both deployments: acceptance, idempotency, every error path."""

from __future__ import annotations

import functools
import gzip
import secrets
import zlib
from concurrent.futures import ThreadPoolExecutor

import orjson
import pytest

from tests.integration.conftest import EXAMPLE, Deployment, example_doc, unique_trip

pytestmark = pytest.mark.integration

MIB = 1024 * 1024


def _trip_rows(dep: Deployment, vehicle_id: str, trip_id: str) -> int:
    return dep.scalar(
        "SELECT count(*) FROM trips WHERE vehicle_id = :v AND trip_id = :t", v=vehicle_id, t=trip_id
    )


def _table_counts(dep: Deployment) -> tuple[int, ...]:
    return tuple(dep.scalar(f"SELECT count(*) FROM {t}") for t in ("trips", "trip_uploads", "jobs"))


def test_the_contract_example_is_accepted_with_202_and_location(deployment: Deployment):
    doc = orjson.loads(EXAMPLE.read_bytes())
    doc["trip_id"] = "example-" + secrets.token_hex(4)  # the example itself, under a key of this test
    response = deployment.upload(orjson.dumps(doc))
    assert response.status_code == 202, response.text
    body = response.json()
    assert body["status"] == "received"
    assert (body["vehicle_id"], body["trip_id"]) == (doc["vehicle_id"], doc["trip_id"])
    assert response.headers["location"] == f"/v1/trips/{body['id']}"
    with deployment.admin() as http:
        trip = http.get(response.headers["location"]).json()
    # the example is 1 s of a standing vehicle: its ingest may already have failed (nothing to orient)
    assert trip["id"] == body["id"] and trip["status"] in ("received", "processing", "failed")


def test_the_verbatim_example_file_is_accepted(deployment: Deployment):
    response = deployment.upload(EXAMPLE.read_bytes())
    assert response.status_code in (200, 202), response.text  # 200 when the other test ran first


def test_gzip_upload_is_accepted_and_the_raw_upload_is_kept_compressed(deployment: Deployment):
    doc = unique_trip()
    plain = orjson.dumps(doc)
    response = deployment.upload(doc, gzipped=True)
    assert response.status_code == 202, response.text
    trip_pk = response.json()["id"]
    encoding, raw = deployment.rows("SELECT encoding, body FROM trip_uploads WHERE trip_pk = :p", p=trip_pk)[
        0
    ]
    assert encoding == "gzip"
    assert gzip.decompress(bytes(raw)) == plain
    assert deployment.scalar("SELECT body_bytes FROM trips WHERE id = :p", p=trip_pk) == len(
        gzip.compress(plain)
    )


def test_plain_upload_is_stored_gzip_compressed(deployment: Deployment):
    doc = unique_trip()
    trip_pk = deployment.upload(doc).json()["id"]
    raw = deployment.scalar("SELECT body FROM trip_uploads WHERE trip_pk = :p", p=trip_pk)
    assert gzip.decompress(bytes(raw)) == orjson.dumps(doc)
    assert len(raw) < len(orjson.dumps(doc))


def test_same_body_again_gives_the_same_trip_and_no_second_row(deployment: Deployment):
    doc = unique_trip()
    first = deployment.upload(doc)
    again = deployment.upload(doc, gzipped=True)  # the same body, compressed: the same content
    assert first.status_code == 202
    assert again.status_code == 200, again.text
    assert again.json()["id"] == first.json()["id"]
    assert again.headers["location"] == first.headers["location"]
    assert _trip_rows(deployment, doc["vehicle_id"], doc["trip_id"]) == 1
    jobs = deployment.scalar("SELECT count(*) FROM jobs WHERE subject = :p", p=first.json()["id"])
    assert jobs == 1


def test_different_body_under_the_same_key_is_409_and_changes_nothing(deployment: Deployment):
    doc = unique_trip()
    first = deployment.upload(doc)
    changed = orjson.loads(orjson.dumps(doc))
    changed["frames"][3]["gnss"]["lat"] += 1e-6
    before = _table_counts(deployment)
    conflict = deployment.upload(changed)
    assert conflict.status_code == 409
    assert conflict.json()["error"] == "conflict"
    assert first.json()["id"] in conflict.json()["message"]
    assert _table_counts(deployment) == before
    raw = deployment.scalar("SELECT body FROM trip_uploads WHERE trip_pk = :p", p=first.json()["id"])
    assert gzip.decompress(bytes(raw)) == orjson.dumps(doc)


def test_twenty_concurrent_identical_uploads_make_one_trip(deployment: Deployment):
    doc = unique_trip()
    body = orjson.dumps(doc)
    with ThreadPoolExecutor(20) as pool:
        responses = list(pool.map(lambda _: deployment.upload(body), range(20)))
    statuses = sorted(r.status_code for r in responses)
    assert statuses == [200] * 19 + [202], [r.text for r in responses if r.status_code not in (200, 202)]
    assert len({r.json()["id"] for r in responses}) == 1
    assert _trip_rows(deployment, doc["vehicle_id"], doc["trip_id"]) == 1
    assert deployment.scalar("SELECT count(*) FROM jobs WHERE subject = :p", p=responses[0].json()["id"]) == 1


def _bad_json_bodies() -> list[tuple[str, bytes, int, str, str]]:
    """(case, body, status, error code, expected location)"""

    def mutate(fn) -> bytes:
        doc = unique_trip()
        fn(doc)
        return orjson.dumps(doc)

    def drop(path: list, key: str):
        def fn(doc):
            target = doc
            for p in path:
                target = target[p]
            del target[key]

        return fn

    def with_literal(literal: bytes) -> bytes:
        body = mutate(lambda d: d.update(sensor_setup={"model": "m", "bev": [-50.0, "HERE"]}))
        return body.replace(b'"HERE"', literal)

    return [
        ("malformed JSON", b'{"schema_version": "1.0", "frames": [', 400, "json", ""),
        ("not an object", b"[1, 2, 3]", 422, "schema", ""),
        ("missing lat", mutate(drop(["frames", 4, "gnss"], "lat")), 422, "schema", "frames[4].gnss.lat"),
        (
            "lat out of range",
            mutate(lambda d: d["frames"][2]["gnss"].update(lat=91.0)),
            422,
            "schema",
            "frames[2].gnss.lat",
        ),
        (
            "unknown field",
            mutate(lambda d: d["frames"][1]["odom"].update(z=0.0)),
            422,
            "schema",
            "frames[1].odom.z",
        ),
        (
            "bad status",
            mutate(lambda d: d["frames"][5]["gnss"].update(status="great")),
            422,
            "schema",
            "frames[5].gnss.status",
        ),
        ("one frame", mutate(lambda d: d.update(frames=d["frames"][:1])), 422, "schema", "frames"),
        ("bad vehicle id", mutate(lambda d: d.update(vehicle_id="a b")), 422, "schema", "vehicle_id"),
        ("bad started_at", mutate(lambda d: d.update(started_at="yesterday")), 422, "schema", "started_at"),
        (
            "element with one point",
            mutate(lambda d: d["frames"][6]["elements"][0].update(points=[[0.0, 0.0]])),
            422,
            "schema",
            "frames[6].elements[0].points",
        ),
        (
            "t not increasing",
            mutate(lambda d: d["frames"][7].update(t=d["frames"][6]["t"])),
            422,
            "time_order",
            "frames[7].t",
        ),
        (
            "unknown schema version",
            mutate(lambda d: d.update(schema_version="2.0")),
            422,
            "version",
            "schema_version",
        ),
        ("missing schema version", mutate(drop([], "schema_version")), 422, "schema", "schema_version"),
        *(
            (
                f"started_at {text!r}",
                mutate(lambda d, text=text: d.update(started_at=text)),
                422,
                "schema",
                "started_at",
            )
            for text in (
                "2026-99-99T99:99:99Z",
                "2026-02-30T08:00:00Z",
                "2026-01-01T25:61:61Z",
                "2026-01-01T08:00:00Z\n",
            )
        ),
        *(
            (
                f"{literal.decode()} in sensor_setup",
                with_literal(literal),
                422,
                "non_finite",
                "sensor_setup.bev[1]",
            )
            for literal in (b"NaN", b"1e999")
        ),
    ]


@pytest.mark.parametrize(
    "case,body,status,error,location",
    _bad_json_bodies(),
    ids=lambda v: v if isinstance(v, str) and " " in v else None,
)
def test_invalid_upload_is_rejected_with_frame_and_field_and_leaves_no_trace(
    deployment, case, body, status, error, location
):
    before = _table_counts(deployment)
    response = deployment.upload(body)
    assert response.status_code == status, response.text
    answer = response.json()
    assert answer["error"] == error
    assert answer["location"] == location
    assert answer["message"]
    if location.startswith("frames["):
        index = location[len("frames[") :].split("]")[0]
        assert f"frame {index}" in answer["message"]
    assert _table_counts(deployment) == before


@pytest.mark.parametrize("literal", [b"NaN", b"Infinity", b"-Infinity", b"1e999"])
def test_non_finite_number_is_rejected(deployment: Deployment, literal: bytes):
    plain = orjson.dumps(unique_trip())
    body = plain.replace(b'"odom":{"x":0.0,', b'"odom":{"x":' + literal + b",", 1)  # frame 0's odom x
    assert body != plain
    before = _table_counts(deployment)
    response = deployment.upload(body)
    assert response.status_code == 422, response.text
    assert response.json()["error"] == "non_finite"
    assert response.json()["location"] == "frames[0].odom.x"
    assert _table_counts(deployment) == before


def test_malformed_and_truncated_gzip_are_400(deployment: Deployment):
    headers = {"Content-Type": "application/json", "Content-Encoding": "gzip"}
    full = gzip.compress(orjson.dumps(unique_trip()))
    with deployment.admin() as http:
        for body in (b"this is not gzip at all", full[: len(full) // 2]):
            response = http.post("/v1/trips", content=body, headers=headers)
            assert response.status_code == 400, response.text
            assert response.json()["error"] == "gzip"


def test_wrong_content_type_or_encoding_is_415(deployment: Deployment):
    body = orjson.dumps(unique_trip())
    with deployment.admin() as http:
        r1 = http.post("/v1/trips", content=body, headers={"Content-Type": "text/plain"})
        r2 = http.post(
            "/v1/trips", content=body, headers={"Content-Type": "application/json", "Content-Encoding": "br"}
        )
    assert (r1.status_code, r1.json()["error"]) == (415, "content_type")
    assert (r2.status_code, r2.json()["error"]) == (415, "content_encoding")


def test_body_over_the_limit_is_413_while_streaming(deployment: Deployment):
    chunk = b" " * MIB

    def body():  # chunked: no Content-Length, the limit is enforced while reading
        for _ in range(40):
            yield chunk

    before = _table_counts(deployment)
    with deployment.admin() as http:
        response = http.post("/v1/trips", content=body(), headers={"Content-Type": "application/json"})
    assert response.status_code == 413
    assert response.json()["error"] == "too_large"
    assert "as sent" in response.json()["message"]
    assert _table_counts(deployment) == before


def test_declared_length_over_the_limit_is_413(deployment: Deployment):
    with deployment.admin() as http:
        response = http.post(
            "/v1/trips", content=b"{" + b" " * (33 * MIB), headers={"Content-Type": "application/json"}
        )
    assert response.status_code == 413


@functools.cache
def _zip_bomb() -> bytes:
    compressor = zlib.compressobj(6, zlib.DEFLATED, 16 + zlib.MAX_WBITS)
    zeros = b"\0" * (16 * MIB)
    return b"".join(compressor.compress(zeros) for _ in range(20)) + compressor.flush()  # 320 MiB inflated


def test_zip_bomb_is_413_after_decompression(deployment: Deployment):
    bomb = _zip_bomb()
    assert len(bomb) < MIB
    before = _table_counts(deployment)
    with deployment.admin() as http:
        response = http.post(
            "/v1/trips",
            content=bomb,
            headers={"Content-Type": "application/json", "Content-Encoding": "gzip"},
        )
    assert response.status_code == 413
    assert "after decompression" in response.json()["message"]
    assert _table_counts(deployment) == before


def test_vehicle_key_uploads_only_for_its_own_vehicle(deployment: Deployment):
    with deployment.admin() as http:
        key = http.post("/v1/keys", json={"role": "vehicle", "vehicle_id": "veh-own"}).json()["key"]
    own = deployment.upload(unique_trip("veh-own"), key=key)
    other = deployment.upload(unique_trip("veh-other"), key=key)
    assert own.status_code == 202
    assert other.status_code == 403 and other.json()["location"] == "vehicle_id"


def test_example_doc_helper_is_the_contract_example():
    assert example_doc()["frames"][0]["t"] == 0.0
