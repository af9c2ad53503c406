"""The compact binary upload (csr_core.upload_binary): round trips, quantisation bounds,
keyframe-only perception, and malformed binaries rejected naming where."""

from __future__ import annotations

import copy
import json
from dataclasses import replace
from pathlib import Path
from typing import Any

import cbor2
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from csr_core import upload_binary
from csr_core.errors import UploadError
from csr_core.upload import validate_upload
from csr_core.upload_binary import Decimals, EncodeOptions, decode, encode, quantisation_bound

pytestmark = pytest.mark.unit

EXAMPLE = json.loads(
    (Path(__file__).resolve().parents[2] / "tests" / "data" / "example-trip.json").read_text()
)


def _numbers(doc: dict[str, Any]) -> dict[str, np.ndarray]:
    """Every number of a document, by field."""
    frames = doc["frames"]
    elements = [e for f in frames for e in f["elements"]]
    return {
        "t": np.array([f["t"] for f in frames]),
        "lat": np.array([f["gnss"]["lat"] for f in frames]),
        "lon": np.array([f["gnss"]["lon"] for f in frames]),
        "odom": np.array([[f["odom"]["x"], f["odom"]["y"]] for f in frames]),
        "yaw": np.array([f["odom"]["yaw"] for f in frames]),
        "points": np.concatenate([np.asarray(e["points"], float) for e in elements]),
        "score": np.array([e["score"] for e in elements if "score" in e]),
    }


def test_the_example_round_trips_bit_identical():
    """The example carries no more decimals than the default steps: nothing is lost."""
    body = encode(EXAMPLE)
    assert decode(body) == EXAMPLE
    assert len(body) < len(json.dumps(EXAMPLE)) / 3


def test_coarser_steps_stay_within_half_a_step():
    decimals = Decimals(t_s=2, latlon_deg=7, odom_m=2, odom_yaw_rad=4, point_m=1, score=2)
    back = decode(encode(EXAMPLE, EncodeOptions(decimals=decimals)))
    validate_upload(back)
    before, after = _numbers(EXAMPLE), _numbers(back)
    steps = {"t": 2, "lat": 7, "lon": 7, "odom": 2, "yaw": 4, "points": 1, "score": 2}
    for name, digits in steps.items():
        error = np.max(np.abs(after[name] - before[name]))
        assert error <= quantisation_bound(digits, np.max(np.abs(before[name]))), (name, error)
    # the steps are real: something did change at 0.1 m for points
    assert np.max(np.abs(after["points"] - before["points"])) > 0.01


def _trip(draw: st.DrawFn) -> dict[str, Any]:
    n = draw(st.integers(2, 6))
    steps = draw(
        st.lists(st.floats(0.001, 10.0, allow_nan=False, allow_infinity=False), min_size=n, max_size=n)
    )
    frames = []
    for i in range(n):
        gnss: dict[str, Any] = {
            "lat": draw(st.floats(-90, 90, allow_nan=False, allow_infinity=False)),
            "lon": draw(st.floats(-180, 180, allow_nan=False, allow_infinity=False)),
            "status": draw(st.sampled_from(upload_binary.GNSS_STATUSES)),
        }
        if draw(st.booleans()):
            gnss["heading_deg"] = draw(st.floats(0, 359.99, allow_nan=False, allow_infinity=False))
        if draw(st.booleans()):
            gnss["std_m"] = draw(st.floats(0.01, 100, allow_nan=False, allow_infinity=False))
        elements = []
        for _ in range(draw(st.integers(0, 3))):
            m = draw(st.integers(2, 5))
            point = st.floats(-1000, 1000, allow_nan=False, allow_infinity=False)
            element: dict[str, Any] = {
                "type": draw(st.sampled_from(upload_binary.ELEMENT_TYPES)),
                "points": [[draw(point), draw(point)] for _ in range(m)],
            }
            if draw(st.booleans()):
                element["style"] = draw(st.sampled_from(upload_binary.DIVIDER_STYLES))
            if draw(st.booleans()):
                element["score"] = draw(st.floats(0, 1, allow_nan=False, allow_infinity=False))
            if draw(st.booleans()):
                element["track_id"] = draw(st.integers(-(2**63), 2**63 - 1))
            elements.append(element)
        frames.append(
            {
                "t": round(sum(steps[: i + 1]), 3),
                "gnss": gnss,
                "odom": {
                    k: draw(st.floats(-1e5, 1e5, allow_nan=False, allow_infinity=False))
                    for k in ("x", "y", "yaw")
                },
                "elements": elements,
            }
        )
    return {
        "schema_version": "1.0",
        "vehicle_id": "veh-1",
        "trip_id": "hyp",
        "started_at": "2026-01-01T00:00:00Z",
        "sensor_setup": {"rate_hz": 10, "nested": {"list": [1.5, "a", None, True]}},
        "frames": frames,
    }


@settings(max_examples=60, deadline=None)
@given(st.composite(_trip)())
def test_any_trip_round_trips_within_the_steps(doc: dict[str, Any]):
    back = decode(encode(doc))
    d = Decimals()
    assert back["sensor_setup"] == doc["sensor_setup"]
    for before, after in zip(doc["frames"], back["frames"], strict=True):
        assert abs(after["t"] - before["t"]) <= quantisation_bound(d.t_s, 100.0)
        for key in ("lat", "lon"):
            assert abs(after["gnss"][key] - before["gnss"][key]) <= quantisation_bound(d.latlon_deg, 180.0)
        assert after["gnss"].keys() == before["gnss"].keys()
        assert after["gnss"]["status"] == before["gnss"]["status"]
        for key, digits in (("heading_deg", d.heading_deg), ("std_m", d.std_m)):
            if key in before["gnss"]:
                assert abs(after["gnss"][key] - before["gnss"][key]) <= quantisation_bound(digits, 360.0)
        for key, digits in (("x", d.odom_m), ("y", d.odom_m), ("yaw", d.odom_yaw_rad)):
            assert abs(after["odom"][key] - before["odom"][key]) <= quantisation_bound(digits, 1e5)
        assert len(after["elements"]) == len(before["elements"])
        for e_before, e_after in zip(before["elements"], after["elements"], strict=True):
            assert e_after.keys() == e_before.keys()
            assert (e_after["type"], e_after.get("style"), e_after.get("track_id")) == (
                e_before["type"],
                e_before.get("style"),
                e_before.get("track_id"),
            )
            if "score" in e_before:
                assert abs(e_after["score"] - e_before["score"]) <= quantisation_bound(d.score)
            error = np.abs(np.asarray(e_after["points"]) - np.asarray(e_before["points"]))
            assert error.max() <= quantisation_bound(d.point_m, 1000.0)


def _moving_trip(n: int = 60) -> dict[str, Any]:
    """A trip driving 1 m per frame along odometry x, two elements per frame."""
    doc = copy.deepcopy(EXAMPLE)
    template = doc["frames"][0]
    doc["frames"] = [
        {
            **copy.deepcopy(template),
            "t": round(0.1 * i, 3),
            "odom": {"x": float(i), "y": 0.0, "yaw": 0.0},
            "elements": copy.deepcopy(template["elements"][:2]),
        }
        for i in range(n)
    ]
    return doc


def test_keyframe_only_keeps_the_elements_of_frames_every_spacing():
    doc = _moving_trip()
    back = decode(encode(doc, EncodeOptions(keyframe_spacing_m=5.0, keyframe_period_s=100.0)))
    with_elements = [i for i, f in enumerate(back["frames"]) if f["elements"]]
    assert with_elements == [*range(0, 60, 5), 59]
    for i in with_elements:
        assert back["frames"][i]["elements"] == doc["frames"][i]["elements"]
    # everything but the dropped elements is kept
    assert [f["odom"] for f in back["frames"]] == [f["odom"] for f in doc["frames"]]
    validate_upload(back)


def test_keyframe_only_keeps_a_frame_every_period_when_standing():
    doc = _moving_trip()
    for frame in doc["frames"]:
        frame["odom"] = {"x": 0.0, "y": 0.0, "yaw": 0.0}
    back = decode(encode(doc, EncodeOptions(keyframe_spacing_m=5.0, keyframe_period_s=1.0)))
    assert [i for i, f in enumerate(back["frames"]) if f["elements"]] == [0, 10, 20, 30, 40, 50, 59]


def test_a_number_too_large_for_its_step_is_refused_by_the_encoder():
    doc = copy.deepcopy(EXAMPLE)
    doc["frames"][3]["odom"]["x"] = 1e13
    with pytest.raises(ValueError, match="frames.odom.x"):
        encode(doc)
    assert (
        decode(encode(doc, EncodeOptions(decimals=replace(Decimals(), odom_m=0))))["frames"][3]["odom"]["x"]
        == 1e13
    )


def _tampered(change) -> bytes:
    raw = cbor2.loads(encode(EXAMPLE))
    change(raw)
    return cbor2.dumps(raw)


@pytest.mark.parametrize(
    ("case", "body", "reason", "location"),
    [
        ("not CBOR", b"\xff\x00garbage", "cbor", ""),
        ("truncated", encode(EXAMPLE)[:-7], "cbor", ""),
        ("bytes after the document", encode(EXAMPLE) + b"\x00", "cbor", ""),
        ("unknown key", _tampered(lambda d: d.update(extra=1)), "binary", "extra"),
        ("unknown column", _tampered(lambda d: d["frames"].update(z=[])), "binary", "frames.z"),
        ("not a map", cbor2.dumps([1, 2, 3]), "binary", ""),
        ("other format", _tampered(lambda d: d.update(format="x")), "binary", "format"),
        ("newer version", _tampered(lambda d: d.update(format_version=2)), "binary", "format_version"),
        ("bad decimals", _tampered(lambda d: d["decimals"].update(point_m=99)), "binary", "decimals.point_m"),
        ("missing column", _tampered(lambda d: d["frames"].pop("lat")), "binary", "frames.lat"),
        ("missing t", _tampered(lambda d: d["frames"].pop("t")), "binary", "frames.t"),
        ("t not an array", _tampered(lambda d: d["frames"].update(t=3)), "binary", "frames.t"),
        ("short column", _tampered(lambda d: d["frames"]["lon"].pop()), "binary", "frames.lon"),
        (
            "text in a column",
            _tampered(lambda d: d["frames"]["yaw"].__setitem__(4, "x")),
            "binary",
            "frames.yaw[4]",
        ),
        (
            "float in a column",
            _tampered(lambda d: d["elements"]["x"].__setitem__(2, 1.5)),
            "binary",
            "elements.x[2]",
        ),
        (
            "unknown status",
            _tampered(lambda d: d["frames"]["status"].__setitem__(5, 9)),
            "binary",
            "frames[5].gnss.status",
        ),
        (
            "unknown type",
            _tampered(lambda d: d["elements"]["type"].__setitem__(1, 6)),
            "binary",
            "elements.type[1]",
        ),
        (
            "points do not add up",
            _tampered(lambda d: d["elements"]["n_points"].__setitem__(0, 1000)),
            "binary",
            "elements.x",
        ),
        (
            "bytes in sensor_setup",
            _tampered(lambda d: d["sensor_setup"].update(blob=b"\x00")),
            "binary",
            "sensor_setup.blob",
        ),
    ],
)
def test_malformed_binary_is_rejected_naming_where(case: str, body: bytes, reason: str, location: str):
    with pytest.raises(UploadError) as err:
        decode(body)
    assert (err.value.reason, err.value.location) == (reason, location), err.value.message
    assert err.value.message


def test_a_schema_violation_in_a_binary_is_named_in_the_decoded_document():
    """The decoder accepts the structure; the schema check names the frame and field, as for JSON."""
    raw = cbor2.loads(encode(EXAMPLE))
    n_first = raw["elements"]["n_points"][0]
    raw["elements"]["n_points"][0] = 1  # the first element keeps only its first point
    del raw["elements"]["x"][1:n_first], raw["elements"]["y"][1:n_first]
    with pytest.raises(UploadError) as err:
        validate_upload(decode(cbor2.dumps(raw)))
    assert (err.value.reason, err.value.location) == ("schema", "frames[0].elements[0].points")


def test_a_cyclic_sensor_setup_is_rejected():
    shared = cbor2.CBORTag(28, {"self": cbor2.CBORTag(29, 0)})  # a map that contains itself
    raw = cbor2.loads(encode(EXAMPLE))
    raw["sensor_setup"] = shared
    with pytest.raises(UploadError) as err:
        decode(cbor2.dumps(raw))
    assert err.value.reason == "binary" and err.value.location.startswith("sensor_setup.self.self")


def test_tracking_runs_on_the_kept_keyframes_of_a_keyframe_only_upload():
    """The single-trip stage tracks one frame every 5 m among the frames that report elements:
    a keyframe-only upload (keyframes every 5.5 m) is tracked on every keyframe, never on an
    empty frame; an upload with every frame's elements is tracked as before."""
    from csr_core.single_trip.keyframes import select_tracking_frames

    n = 200
    poses = np.column_stack([0.9 * np.arange(n), np.zeros(n), np.zeros(n)])  # 0.9 m per frame
    t = 0.1 * np.arange(n)
    doc = _moving_trip(n)
    for i, frame in enumerate(doc["frames"]):
        frame["odom"]["x"] = float(poses[i, 0])
    back = decode(encode(doc, EncodeOptions(keyframe_spacing_m=5.5, keyframe_period_s=100.0)))
    perceived = np.array([bool(f["elements"]) for f in back["frames"]])
    tracked = select_tracking_frames(poses, t, 5.0, 100.0, perceived=perceived)
    assert perceived[tracked].all()
    assert set(tracked) == set(np.flatnonzero(perceived)) - {n - 1}  # the last is a keyframe only
    everything = select_tracking_frames(poses, t, 5.0, 100.0, perceived=np.ones(n, bool))
    np.testing.assert_array_equal(everything, select_tracking_frames(poses, t, 5.0, 100.0))
