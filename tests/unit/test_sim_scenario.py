"""Simulator scenario folders: contract section 5 layout, determinism, schema validity."""

import csv
import gzip
import hashlib
import json
import pathlib

import jsonschema
import orjson
import pytest

from csr_core.sim import simulate_scenario
from csr_core.upload import decode_trip, validate_upload_json

pytestmark = pytest.mark.unit

# the vendored copy of the contract's schema (test_contract_schema checks it is the contract's)
SCHEMA = pathlib.Path(__file__).resolve().parents[2] / "csr_core" / "schemas" / "trip-upload.schema.json"
TRIP_M = 120.0


def _hashes(folder: pathlib.Path) -> dict[str, str]:
    return {
        str(p.relative_to(folder)): hashlib.sha256(p.read_bytes()).hexdigest()
        for p in sorted(folder.rglob("*"))
        if p.is_file()
    }


@pytest.fixture(scope="module")
def scenario(tmp_path_factory):
    out = tmp_path_factory.mktemp("scen") / "urban"
    meta = simulate_scenario("urban", 3, "standard", 7, out, trip_length_m=TRIP_M)
    return out, meta


def test_folder_layout_follows_contract_section_5(scenario):
    out, meta = scenario
    doc = json.loads((out / "scenario.json").read_text())
    assert {"name", "origin", "profile"} <= doc.keys()
    assert set(doc["origin"]) == {"lat", "lon"}
    assert (
        doc["profile"]["name"] == "standard" and "gnss" in doc["profile"] and "perception" in doc["profile"]
    )
    trips = sorted(p.name for p in (out / "trips").iterdir())
    poses = sorted(p.name for p in (out / "truth" / "poses").iterdir())
    assert len(trips) == 3
    assert [t.removesuffix(".json.gz") for t in trips] == [p.removesuffix(".csv") for p in poses]
    for name in trips:
        vehicle_id, trip_id = name.removesuffix(".json.gz").split("__")
        upload = orjson.loads(gzip.decompress((out / "trips" / name).read_bytes()))
        assert (upload["vehicle_id"], upload["trip_id"]) == (vehicle_id, trip_id)
    geo = json.loads((out / "truth" / "map.geojson").read_text())
    assert geo["type"] == "FeatureCollection"
    kinds = {f["properties"]["type"] for f in geo["features"]}
    assert {"lane_divider", "road_boundary", "centerline", "stop_line", "crosswalk"} <= kinds
    for f in geo["features"]:
        gtype = f["geometry"]["type"]
        assert gtype == ("Polygon" if f["properties"]["type"] == "crosswalk" else "LineString")
        if f["properties"]["type"] == "lane_divider":
            assert f["properties"]["style"] in ("solid", "dashed", "double", "unknown")
        if gtype == "Polygon":
            ring = f["geometry"]["coordinates"][0]
            assert ring[0] == ring[-1] and len(ring) >= 4


def test_every_trip_validates_against_the_upload_schema(scenario):
    out, _ = scenario
    schema = json.loads(SCHEMA.read_text())
    validator = jsonschema.Draft202012Validator(schema, format_checker=jsonschema.FormatChecker())
    for path in sorted((out / "trips").glob("*.json.gz")):
        body = gzip.decompress(path.read_bytes())
        doc = validate_upload_json(body)
        validator.validate(orjson.loads(body))
        trip = decode_trip(doc)
        assert trip.n_frames > 10
        assert sum(len(f) for f in trip.elements) > 0


def test_truth_poses_have_one_row_per_uploaded_frame(scenario):
    out, meta = scenario
    for info in meta["trips"]:
        with open(out / "truth" / "poses" / f"{info['key']}.csv") as f:
            rows = list(csv.reader(f))
        assert rows[0] == ["t", "lat", "lon", "heading_deg"]
        upload = orjson.loads(gzip.decompress((out / "trips" / f"{info['key']}.json.gz").read_bytes()))
        assert len(rows) - 1 == len(upload["frames"]) == info["frames"]
        assert [float(r[0]) for r in rows[1:]] == [fr["t"] for fr in upload["frames"]]


def test_same_seed_gives_byte_identical_folder_and_another_seed_differs(scenario, tmp_path):
    out, _ = scenario
    again = tmp_path / "again"
    simulate_scenario("urban", 3, "standard", 7, again, trip_length_m=TRIP_M)
    assert _hashes(again) == _hashes(out)
    other = tmp_path / "other"
    simulate_scenario("urban", 3, "standard", 8, other, trip_length_m=TRIP_M)
    a, b = _hashes(out), _hashes(other)
    assert a["truth/map.geojson"] == b["truth/map.geojson"]  # the world does not depend on the seed
    assert {k for k in a if k.startswith("trips/")} != {k for k in b if k.startswith("trips/")} or any(
        a[k] != b[k] for k in a if k.startswith("trips/")
    )


def test_several_vehicles_and_unique_trip_ids(tmp_path):
    meta = simulate_scenario("rural", 7, "hard", 3, tmp_path / "s", trip_length_m=60.0)
    keys = [t["key"] for t in meta["trips"]]
    vehicles = {k.split("__")[0] for k in keys}
    assert len(vehicles) >= 3
    assert len(set(keys)) == len(keys)


def test_unknown_world_or_profile_is_an_error(tmp_path):
    with pytest.raises(ValueError, match="unknown world"):
        simulate_scenario("moon", 1, "standard", 0, tmp_path / "x")
    with pytest.raises(ValueError, match="unknown profile"):
        simulate_scenario("urban", 1, "sunny", 0, tmp_path / "y")


def test_cli_writes_a_scenario(tmp_path, capsys):
    from services.cli import main

    out = tmp_path / "cli"
    assert (
        main(
            [
                "simulate",
                "--world",
                "roundabout",
                "--trips",
                "2",
                "--seed",
                "1",
                "--out",
                str(out),
                "--trip-length-m",
                "80",
            ]
        )
        == 0
    )
    assert len(list((out / "trips").glob("*.json.gz"))) == 2
    assert (out / "truth" / "map.geojson").exists() and (out / "scenario.json").exists()
    assert "csr simulate: roundabout-standard-n2-s1: 2 trips" in capsys.readouterr().out


def test_profiles_share_the_drives_of_a_seed(tmp_path):
    a = simulate_scenario("highway", 2, "standard", 4, tmp_path / "a", trip_length_m=100.0)
    b = simulate_scenario("highway", 2, "hard", 4, tmp_path / "b", trip_length_m=100.0)
    assert [t["key"] for t in a["trips"]] == [t["key"] for t in b["trips"]]
    assert _hashes(tmp_path / "a" / "truth") == _hashes(tmp_path / "b" / "truth")
    assert _hashes(tmp_path / "a" / "trips") != _hashes(tmp_path / "b" / "trips")
