"""Frame-batch checking and decoding (csr_core.upload_frames): the same verdicts, errors and trip as
the whole-body validator, with batches small enough that every case crosses a batch boundary."""

from __future__ import annotations

import copy
import json
import tracemalloc

import numpy as np
import orjson
import pytest

from csr_core import upload_frames
from csr_core.errors import UploadError
from csr_core.upload import decode_trip, validate_upload_json
from csr_core.upload_frames import check_upload_json, decode_upload_json
from tests.unit.test_upload import EXAMPLE, SCHEMA_VIOLATIONS

pytestmark = pytest.mark.unit


@pytest.fixture(autouse=True)
def _small_batches(monkeypatch):
    monkeypatch.setattr(upload_frames, "BATCH_JSON_BYTES", 3 * len(json.dumps(EXAMPLE["frames"][0])))


def _error(check, body: bytes) -> dict[str, str]:
    with pytest.raises(UploadError) as caught:
        check(body)
    return caught.value.as_dict()


def _same_error(body: bytes) -> dict[str, str]:
    whole = _error(validate_upload_json, body)
    assert _error(check_upload_json, body) == whole
    return whole


def test_the_example_passes_with_its_head():
    head = check_upload_json(json.dumps(EXAMPLE).encode())
    assert (head.vehicle_id, head.trip_id, head.started_at, head.schema_version) == (
        EXAMPLE["vehicle_id"],
        EXAMPLE["trip_id"],
        EXAMPLE["started_at"],
        EXAMPLE["schema_version"],
    )
    assert head.n_frames == len(EXAMPLE["frames"])


@pytest.mark.parametrize("case,mutate,location", SCHEMA_VIOLATIONS, ids=[c[0] for c in SCHEMA_VIOLATIONS])
def test_every_schema_violation_gives_the_whole_body_error(case, mutate, location):
    doc = copy.deepcopy(EXAMPLE)
    mutate(doc)
    assert _same_error(json.dumps(doc).encode())["location"] == location, case


@pytest.mark.parametrize(
    "edit",
    [
        lambda d: d["frames"][7].__setitem__("t", d["frames"][6]["t"]),  # time order, in a later batch
        lambda d: d.__setitem__("schema_version", "1.1"),
        lambda d: d.__setitem__("started_at", "2024-02-30T00:00:00Z"),
        lambda d: d.__setitem__("sensor_setup", {"gain": 1e999}),
        lambda d: (d["frames"][8]["gnss"].__setitem__("lat", 99.0), d.__setitem__("started_at", "x")),
    ],
    ids=["time order", "version", "started_at", "sensor_setup", "schema before started_at"],
)
def test_semantic_errors_and_their_order_match(edit):
    doc = copy.deepcopy(EXAMPLE)
    edit(doc)
    _same_error(json.dumps(doc).replace("Infinity", "1e999").encode())


@pytest.mark.parametrize("literal", ["NaN", "1e400"])
def test_non_finite_numbers_in_a_later_batch(literal):
    doc = copy.deepcopy(EXAMPLE)
    doc["frames"][7]["odom"]["yaw"] = "MARK"
    body = json.dumps(doc).replace('"MARK"', literal).encode()
    assert _same_error(body)["error"] == "non_finite"


@pytest.mark.parametrize("body", [b'{"frames": [}', b"[1, 2]", b'{"frames": {}}', b"", b'{"frames": [{}, ]}'])
def test_bodies_that_cannot_be_split_give_the_whole_body_error(body):
    _same_error(body)


def test_malformed_json_inside_a_later_frame_gives_the_whole_body_error():
    body = json.dumps(EXAMPLE).encode()
    at = body.index(b'"odom"', len(body) // 2)
    _same_error(body[:at] + b"'odom'" + body[at + 6 :])


def test_more_frames_than_the_limit_are_refused_naming_both():
    n = len(EXAMPLE["frames"])
    with pytest.raises(UploadError) as caught:
        check_upload_json(json.dumps(EXAMPLE).encode(), max_frames=n - 1)
    assert (caught.value.reason, caught.value.location) == ("too_many_frames", "frames")
    assert f"{n} frames" in caught.value.message and f"limit of {n - 1}" in caught.value.message
    assert check_upload_json(json.dumps(EXAMPLE).encode(), max_frames=n).n_frames == n


def test_decoding_by_batches_gives_the_same_trip():
    body = json.dumps(EXAMPLE).encode()
    expected, trip = decode_trip(validate_upload_json(body)), decode_upload_json(body)
    for name in (
        "timestamps_s",
        "gnss_lonlat_deg",
        "gnss_status",
        "gnss_std_m",
        "gnss_heading_deg",
        "odom_xyyaw",
    ):
        np.testing.assert_array_equal(getattr(trip, name), getattr(expected, name), err_msg=name)
    assert (trip.vehicle_id, trip.trip_id, trip.started_at, trip.sensor_setup) == (
        expected.vehicle_id,
        expected.trip_id,
        expected.started_at,
        expected.sensor_setup,
    )
    assert len(trip.elements) == len(expected.elements)
    for mine, theirs in zip(trip.elements, expected.elements, strict=True):
        assert [(e.type, e.style, e.track_id) for e in mine] == [
            (e.type, e.style, e.track_id) for e in theirs
        ]
        for a, b in zip(mine, theirs, strict=True):
            np.testing.assert_array_equal(a.points_xy_vehicle, b.points_xy_vehicle)
            np.testing.assert_array_equal(a.score, b.score)


def _many_small_frames(n: int) -> bytes:
    frame = EXAMPLE["frames"][0]
    frames = [{**frame, "t": 0.1 * i, "elements": []} for i in range(n)]
    return orjson.dumps({**EXAMPLE, "frames": frames})


def _peak_bytes(fn, body: bytes) -> int:
    tracemalloc.start()
    try:
        fn(body)
        return tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()


def test_checking_and_decoding_hold_a_fraction_of_the_parsed_tree(monkeypatch):
    monkeypatch.setattr(upload_frames, "BATCH_JSON_BYTES", 64 * 1024)
    body = _many_small_frames(20_000)
    whole = _peak_bytes(validate_upload_json, body)
    assert _peak_bytes(check_upload_json, body) < 0.8 * len(body) < whole / 4
    assert _peak_bytes(decode_upload_json, body) < 1.5 * len(body)


def test_a_refused_body_can_be_freed_while_its_error_is_alive():
    doc = copy.deepcopy(EXAMPLE)
    doc["frames"][8]["gnss"]["lat"] = 99.0
    body = bytearray(json.dumps(doc).encode())
    with pytest.raises(UploadError) as caught:
        check_upload_json(body)
    assert caught.value.location == "frames[8].gnss.lat"
    body.clear()  # no view into the body is left in the error's traceback
