"""Upload validation (csr_core.upload): the pydantic-core validator agrees with the contract's JSON
Schema on the example and on every kind of violation, and its errors name the frame and field."""

from __future__ import annotations

import copy
import json
from pathlib import Path

import jsonschema
import pytest

from csr_core.errors import UploadError
from csr_core.upload import validate_upload, validate_upload_json

pytestmark = pytest.mark.unit

ROOT = Path(__file__).resolve().parents[2]
SCHEMA = json.loads((ROOT / "csr_core" / "schemas" / "trip-upload.schema.json").read_text())
EXAMPLE = json.loads((ROOT / "tests" / "data" / "example-trip.json").read_text())
JSONSCHEMA = jsonschema.Draft202012Validator(
    SCHEMA, format_checker=jsonschema.Draft202012Validator.FORMAT_CHECKER
)


def _set(path: tuple, value):
    def fn(doc):
        target = doc
        for p in path[:-1]:
            target = target[p]
        target[path[-1]] = value

    return fn


def _del(path: tuple):
    def fn(doc):
        target = doc
        for p in path[:-1]:
            target = target[p]
        del target[path[-1]]

    return fn


# (case, mutation, expected location)
SCHEMA_VIOLATIONS = [
    ("missing schema_version", _del(("schema_version",)), "schema_version"),
    ("missing frames", _del(("frames",)), "frames"),
    ("extra top-level field", _set(("extra",), 1), "extra"),
    ("vehicle_id pattern", _set(("vehicle_id",), "no spaces"), "vehicle_id"),
    ("vehicle_id too long", _set(("vehicle_id",), "v" * 65), "vehicle_id"),
    ("trip_id not a string", _set(("trip_id",), 7), "trip_id"),
    ("sensor_setup not an object", _set(("sensor_setup",), []), "sensor_setup"),
    ("frames empty", _set(("frames",), []), "frames"),
    ("t negative", _set(("frames", 0, "t"), -1.0), "frames[0].t"),
    ("t a string", _set(("frames", 2, "t"), "0.2"), "frames[2].t"),
    ("missing gnss", _del(("frames", 3, "gnss")), "frames[3].gnss"),
    ("lat over 90", _set(("frames", 4, "gnss", "lat"), 90.5), "frames[4].gnss.lat"),
    ("lon under -180", _set(("frames", 4, "gnss", "lon"), -180.5), "frames[4].gnss.lon"),
    ("heading 360", _set(("frames", 5, "gnss", "heading_deg"), 360.0), "frames[5].gnss.heading_deg"),
    ("std_m zero", _set(("frames", 5, "gnss", "std_m"), 0.0), "frames[5].gnss.std_m"),
    ("status unknown", _set(("frames", 6, "gnss", "status"), "rtk"), "frames[6].gnss.status"),
    ("odom missing yaw", _del(("frames", 7, "odom", "yaw")), "frames[7].odom.yaw"),
    ("odom bool", _set(("frames", 7, "odom", "x"), True), "frames[7].odom.x"),
    (
        "element type unknown",
        _set(("frames", 8, "elements", 0, "type"), "tree"),
        "frames[8].elements[0].type",
    ),
    (
        "element one point",
        _set(("frames", 8, "elements", 0, "points"), [[0.0, 0.0]]),
        "frames[8].elements[0].points",
    ),
    (
        "element point of 3",
        _set(("frames", 8, "elements", 0, "points"), [[0.0, 0.0, 0.0], [1.0, 1.0, 1.0]]),
        "frames[8].elements[0].points[0]",
    ),
    ("score over 1", _set(("frames", 9, "elements", 0, "score"), 1.5), "frames[9].elements[0].score"),
    ("track_id float", _set(("frames", 9, "elements", 0, "track_id"), 1.5), "frames[9].elements[0].track_id"),
    ("style unknown", _set(("frames", 9, "elements", 0, "style"), "zigzag"), "frames[9].elements[0].style"),
]


def test_example_is_valid_for_both():
    JSONSCHEMA.validate(EXAMPLE)
    assert validate_upload_json(json.dumps(EXAMPLE).encode())["trip_id"] == EXAMPLE["trip_id"]


@pytest.mark.parametrize("case,mutate,location", SCHEMA_VIOLATIONS, ids=[c[0] for c in SCHEMA_VIOLATIONS])
def test_violation_rejected_by_both_with_location(case, mutate, location):
    doc = copy.deepcopy(EXAMPLE)
    mutate(doc)
    assert not JSONSCHEMA.is_valid(doc), case
    with pytest.raises(UploadError) as caught:
        validate_upload_json(json.dumps(doc).encode())
    error = caught.value
    assert error.reason in ("schema", "version")
    assert error.location == location
    if location.startswith("frames["):
        frame = location.split("]")[0].removeprefix("frames[")
        assert error.message.startswith(f"frame {frame}, field ")
    assert error.as_dict() == {"error": error.reason, "location": location, "message": error.message}


def test_unknown_schema_version_is_its_own_reason():
    doc = copy.deepcopy(EXAMPLE)
    doc["schema_version"] = "1.1"
    assert not JSONSCHEMA.is_valid(doc)
    with pytest.raises(UploadError) as caught:
        validate_upload_json(json.dumps(doc).encode())
    assert (caught.value.reason, caught.value.location) == ("version", "schema_version")
    assert "'1.1'" in caught.value.message


def test_t_not_strictly_increasing_names_the_frame():
    doc = copy.deepcopy(EXAMPLE)
    doc["frames"][4]["t"] = doc["frames"][3]["t"]
    assert JSONSCHEMA.is_valid(doc)  # beyond the schema: the contract's rule
    with pytest.raises(UploadError) as caught:
        validate_upload_json(json.dumps(doc).encode())
    assert (caught.value.reason, caught.value.location) == ("time_order", "frames[4].t")
    assert caught.value.message.startswith("frame 4, field t:")


@pytest.mark.parametrize("literal", ["NaN", "Infinity", "-Infinity", "1e400"])
def test_non_finite_numbers_are_rejected(literal):
    body = json.dumps(EXAMPLE).replace('"yaw": 0.0', f'"yaw": {literal}', 1).encode()
    assert body != json.dumps(EXAMPLE).encode()
    with pytest.raises(UploadError) as caught:
        validate_upload_json(body)
    assert (caught.value.reason, caught.value.location) == ("non_finite", "frames[0].odom.yaw")


def test_malformed_json_is_reason_json():
    with pytest.raises(UploadError) as caught:
        validate_upload_json(b'{"frames": [}')
    assert caught.value.reason == "json"


def test_parsed_documents_validate_the_same():
    assert validate_upload(copy.deepcopy(EXAMPLE))["vehicle_id"] == EXAMPLE["vehicle_id"]
    doc = copy.deepcopy(EXAMPLE)
    doc["frames"][1]["gnss"]["lat"] = 100.0
    with pytest.raises(UploadError) as caught:
        validate_upload(doc)
    assert caught.value.location == "frames[1].gnss.lat"


def test_missing_schema_version_is_a_schema_violation():
    doc = copy.deepcopy(EXAMPLE)
    del doc["schema_version"]
    with pytest.raises(UploadError) as caught:
        validate_upload_json(json.dumps(doc).encode())
    assert (caught.value.reason, caught.value.location) == ("schema", "schema_version")


@pytest.mark.parametrize("version", [1.0, None, "2.0"])
def test_a_schema_version_other_than_the_known_one_is_version(version):
    doc = copy.deepcopy(EXAMPLE)
    doc["schema_version"] = version
    with pytest.raises(UploadError) as caught:
        validate_upload_json(json.dumps(doc).encode())
    assert (caught.value.reason, caught.value.location) == ("version", "schema_version")


@pytest.mark.parametrize("literal", ["NaN", "1e999", "-Infinity"])
def test_non_finite_numbers_in_sensor_setup_are_rejected_with_their_path(literal):
    doc = copy.deepcopy(EXAMPLE)
    doc["sensor_setup"] = {"model": "m", "ranges": [1.0, {"max_m": "HERE"}]}
    body = json.dumps(doc).replace('"HERE"', literal).encode()
    with pytest.raises(UploadError) as caught:
        validate_upload_json(body)
    assert (caught.value.reason, caught.value.location) == ("non_finite", "sensor_setup.ranges[1].max_m")


@pytest.mark.parametrize(
    "started_at",
    [
        "2026-99-99T99:99:99Z",
        "2026-02-30T08:00:00Z",
        "2026-01-01T25:61:61Z",
        "2026-01-01T08:00:00Z\n",
        "2026-01-01T08:00:00+24:00",
        "2026-01-01T08:00:00.1234567890Z",
        "2026-01-0\u0661T08:00:00Z",
    ],
)
def test_started_at_must_be_an_rfc3339_date_time(started_at):
    doc = copy.deepcopy(EXAMPLE)
    doc["started_at"] = started_at
    with pytest.raises(UploadError) as caught:
        validate_upload_json(json.dumps(doc).encode())
    assert (caught.value.reason, caught.value.location) == ("schema", "started_at")


@pytest.mark.parametrize(
    "started_at", ["2024-02-29T00:00:00Z", "2026-12-31T23:59:60Z", "2026-01-01t08:00:00.5+01:30"]
)
def test_rfc3339_date_times_are_accepted(started_at):
    doc = copy.deepcopy(EXAMPLE)
    doc["started_at"] = started_at
    assert validate_upload_json(json.dumps(doc).encode())["started_at"] == started_at
