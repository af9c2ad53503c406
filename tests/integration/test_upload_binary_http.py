"""The compact binary upload (``application/vnd.csr.trip+cbor``) through the real server, on both
deployments: ingested like JSON with the same reconstruction, idempotent, stored as sent, and
rejected with the same error answers."""

from __future__ import annotations

import gzip
import secrets
from typing import Any

import cbor2
import httpx
import numpy as np
import orjson
import pytest

from csr_core import upload_binary
from csr_core.sim import simulate_scenario
from csr_core.upload_binary import Decimals, EncodeOptions
from services.reconstructions import decode_arrays
from tests.integration.conftest import Deployment, moving_trip, unique_trip, wait_until

pytestmark = pytest.mark.integration

CBOR = upload_binary.MEDIA_TYPE


@pytest.fixture(scope="session")
def simulated_doc(tmp_path_factory) -> dict[str, Any]:
    """One simulated 300 m urban trip (standard sensor profile), as its vehicle uploads it."""
    out = tmp_path_factory.mktemp("sim-binary")
    simulate_scenario("urban", n_trips=1, profile="standard", seed=5, out_dir=out, trip_length_m=300.0)
    (path,) = sorted((out / "trips").glob("*.json.gz"))
    return orjson.loads(gzip.decompress(path.read_bytes()))


def _post(dep: Deployment, body: bytes, *, content_type: str = CBOR, gzipped: bool = False) -> httpx.Response:
    headers = {"Content-Type": content_type}
    if gzipped:
        body, headers["Content-Encoding"] = gzip.compress(body), "gzip"
    with dep.admin() as http:
        return http.post("/v1/trips", content=body, headers=headers)


def _counts(dep: Deployment) -> tuple[int, ...]:
    return tuple(dep.scalar(f"SELECT count(*) FROM {t}") for t in ("trips", "trip_uploads", "jobs"))


def _under_new_key(doc: dict[str, Any]) -> dict[str, Any]:
    return {**doc, "trip_id": "b-" + secrets.token_hex(6)}


def _ingested(dep: Deployment, trip_pk: str) -> dict[str, np.ndarray]:
    def stored() -> Any:
        status, error = dep.rows("SELECT status, error FROM trips WHERE id = :p", p=trip_pk)[0]
        assert status != "failed", f"trip {trip_pk} failed: {error}"
        return dep.scalar("SELECT arrays FROM trip_reconstructions WHERE trip_pk = :p", p=trip_pk)

    return decode_arrays(bytes(wait_until(stored, timeout_s=300, what=f"trip {trip_pk} ingested")))


def test_a_binary_upload_is_ingested_with_the_json_uploads_reconstruction(
    deployment: Deployment, simulated_doc
):
    as_json = _under_new_key(simulated_doc)
    as_binary = _under_new_key(simulated_doc)
    coarse = _under_new_key(simulated_doc)
    json_answer = deployment.upload(as_json, gzipped=True)
    binary_answer = _post(deployment, upload_binary.encode(as_binary), gzipped=True)
    centimetre = EncodeOptions(decimals=Decimals(point_m=2, latlon_deg=8))
    coarse_answer = _post(deployment, upload_binary.encode(coarse, centimetre))
    for answer in (json_answer, binary_answer, coarse_answer):
        assert answer.status_code == 202, answer.text
    assert binary_answer.json()["trip_id"] == as_binary["trip_id"]
    assert binary_answer.json()["n_frames"] == len(simulated_doc["frames"])
    reference = _ingested(deployment, json_answer.json()["id"])
    # the default steps are the simulator's own precision: the same numbers, the same poses
    lossless = _ingested(deployment, binary_answer.json()["id"])
    np.testing.assert_array_equal(lossless["poses_xyyaw_world"], reference["poses_xyyaw_world"])
    np.testing.assert_array_equal(lossless["keyframe_indices"], reference["keyframe_indices"])
    # 1 cm points and 1e-8 degree (1 mm) fixes: the smoothing moves by a fraction of the GNSS
    # noise (decimetres here), the trip's element count stays
    lossy = _ingested(deployment, coarse_answer.json()["id"])
    offsets_m = np.linalg.norm(
        lossy["poses_xyyaw_world"][:, :2] - reference["poses_xyyaw_world"][:, :2], axis=1
    )
    assert offsets_m.max() < 0.1, offsets_m.max()
    n_instances = {
        kind: deployment.scalar(
            "SELECT n_instances FROM trip_reconstructions WHERE trip_pk = :p", p=answer.json()["id"]
        )
        for kind, answer in (("json", json_answer), ("binary", binary_answer), ("coarse", coarse_answer))
    }
    assert n_instances["binary"] == n_instances["json"], n_instances
    assert abs(n_instances["coarse"] - n_instances["json"]) <= 0.1 * n_instances["json"], n_instances


def test_the_raw_binary_upload_is_kept_as_sent(deployment: Deployment):
    body = upload_binary.encode(unique_trip())
    answer = _post(deployment, body)
    assert answer.status_code == 202, answer.text
    encoding, raw = deployment.rows(
        "SELECT encoding, body FROM trip_uploads WHERE trip_pk = :p", p=answer.json()["id"]
    )[0]
    assert encoding == "cbor+gzip"
    assert gzip.decompress(bytes(raw)) == body


def test_binary_resend_is_200_and_other_content_or_the_json_form_is_409(deployment: Deployment):
    doc = unique_trip()
    body = upload_binary.encode(doc)
    first = _post(deployment, body)
    assert first.status_code == 202, first.text
    again = _post(deployment, body, gzipped=True)  # the same binary, compressed: the same upload
    assert again.status_code == 200, again.text
    assert again.json()["id"] == first.json()["id"]
    assert again.headers["location"] == first.headers["location"]
    before = _counts(deployment)
    changed = orjson.loads(orjson.dumps(doc))
    changed["frames"][3]["gnss"]["lat"] += 1e-6
    conflict = _post(deployment, upload_binary.encode(changed))
    assert conflict.status_code == 409 and conflict.json()["error"] == "conflict", conflict.text
    # the JSON form of the same trip is another body (the binary is quantised): 409 as well
    json_form = deployment.upload(doc)
    assert json_form.status_code == 409 and json_form.json()["location"] == "trip_id", json_form.text
    assert _counts(deployment) == before


def _tampered(change) -> bytes:
    raw = cbor2.loads(upload_binary.encode(unique_trip()))
    change(raw)
    return cbor2.dumps(raw)


def _bad_binaries() -> list[tuple[str, bytes, int, str, str]]:
    """(case, body, status, error code, expected location)"""
    return [
        ("not CBOR", b"\xff\xfe not cbor", 400, "cbor", ""),
        ("truncated", upload_binary.encode(unique_trip())[:-5], 400, "cbor", ""),
        ("a column short", _tampered(lambda d: d["frames"]["t"].pop()), 422, "binary", "frames.lat"),
        (
            "text in a column",
            _tampered(lambda d: d["frames"]["x"].__setitem__(2, "1")),
            422,
            "binary",
            "frames.x[2]",
        ),
        (
            "lat out of range",
            _tampered(lambda d: d["frames"]["lat"].__setitem__(2, 10**11)),
            422,
            "schema",
            "frames[2].gnss.lat",
        ),
        (
            "t not increasing",
            _tampered(lambda d: d["frames"]["t"].__setitem__(7, 0)),
            422,
            "time_order",
            "frames[7].t",
        ),
        (
            "unknown schema version",
            _tampered(lambda d: d.update(schema_version="2.0")),
            422,
            "version",
            "schema_version",
        ),
        ("bad vehicle id", _tampered(lambda d: d.update(vehicle_id="a b")), 422, "schema", "vehicle_id"),
        (
            "NaN in sensor_setup",
            _tampered(lambda d: d["sensor_setup"].update(gain=float("nan"))),
            422,
            "non_finite",
            "sensor_setup.gain",
        ),
    ]


@pytest.mark.parametrize(("case", "body", "status", "error", "location"), _bad_binaries())
def test_a_bad_binary_is_rejected_naming_where_and_stores_nothing(
    deployment: Deployment, case: str, body: bytes, status: int, error: str, location: str
):
    before = _counts(deployment)
    for gzipped in (False, True):
        answer = _post(deployment, body, gzipped=gzipped)
        assert answer.status_code == status, (case, answer.text)
        assert set(answer.json()) == {"error", "location", "message"}
        assert (answer.json()["error"], answer.json()["location"]) == (error, location), answer.text
    assert _counts(deployment) == before


@pytest.mark.parametrize(
    "content_type", ["application/cbor", "application/x-protobuf", "text/plain", "application/vnd.csr.trip"]
)
def test_an_unknown_content_type_is_415_naming_both_accepted_types(deployment: Deployment, content_type: str):
    answer = _post(deployment, upload_binary.encode(unique_trip()), content_type=content_type)
    assert answer.status_code == 415 and answer.json()["error"] == "content_type", answer.text
    assert "application/json" in answer.json()["message"] and CBOR in answer.json()["message"]


def test_the_content_type_may_carry_parameters_and_any_case(deployment: Deployment):
    body = upload_binary.encode(unique_trip())
    answer = _post(deployment, body, content_type="Application/VND.csr.trip+CBOR; charset=binary")
    assert answer.status_code == 202, answer.text


def test_the_fleet_uploads_a_scenario_as_binary(deployment: Deployment, tmp_path):
    from services import fleet

    doc = unique_trip()
    (tmp_path / "trips").mkdir()
    path = tmp_path / "trips" / f"{doc['vehicle_id']}__{doc['trip_id']}.json.gz"
    path.write_bytes(gzip.compress(orjson.dumps(doc)))
    with fleet.client_for(deployment.base_url, deployment.admin_key) as http:
        ids = fleet.upload_scenario(http, tmp_path, progress=False, binary=EncodeOptions())
    (trip_pk,) = ids.values()
    encoding, raw = deployment.rows("SELECT encoding, body FROM trip_uploads WHERE trip_pk = :p", p=trip_pk)[
        0
    ]
    assert encoding == "cbor+gzip"
    assert gzip.decompress(bytes(raw)) == upload_binary.encode(doc)


def test_csr_encode_trip_and_decode_trip_round_trip_the_example(tmp_path):
    from services.cli import main

    source = tmp_path / "trip.json"
    source.write_bytes(orjson.dumps(unique_trip()))
    assert main(["encode-trip", str(source), str(tmp_path / "trip.cbor.gz"), "--gzip"]) == 0
    assert main(["decode-trip", str(tmp_path / "trip.cbor.gz"), str(tmp_path / "back.json")]) == 0
    assert orjson.loads((tmp_path / "back.json").read_bytes()) == orjson.loads(source.read_bytes())
    keyframes = tmp_path / "keyframes.cbor"
    assert main(["encode-trip", str(source), str(keyframes), "--keyframe-spacing-m", "5"]) == 0
    assert upload_binary.decode(keyframes.read_bytes())["frames"][1]["elements"] == []
    source.write_bytes(b'{"frames": []}')
    assert main(["encode-trip", str(source), str(tmp_path / "bad.cbor")]) == 2


def test_a_binary_trip_goes_through_the_tile_jobs_to_its_poses(make_isolated):
    """The tile jobs read the stored binary too: the trip is aligned and has a pose per frame."""
    dep = make_isolated("embedded")
    dep.start_server()
    doc = moving_trip()
    answer = _post(dep, upload_binary.encode(doc), gzipped=True)
    assert answer.status_code == 202, answer.text
    trip_pk = answer.json()["id"]
    _ingested(dep, trip_pk)
    dep.wait_idle(timeout_s=300)
    with dep.admin() as http:
        http.post("/v1/process").raise_for_status()
    wait_until(
        lambda: dep.scalar("SELECT status FROM trips WHERE id = :p", p=trip_pk) == "aligned",
        timeout_s=300,
        what="the binary trip aligned",
    )
    with dep.admin() as http:
        poses = http.get(f"/v1/trips/{trip_pk}/poses").raise_for_status().json()["frames"]
    assert [p["t"] for p in poses] == [f["t"] for f in doc["frames"]]
