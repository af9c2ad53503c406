"""`csr reconstruct` as a subprocess on a small simulated scenario (contract sections 4-6), and
the evaluator on its output."""

from __future__ import annotations

import gzip
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import orjson
import pytest

from csr_core.bench.evaluate import evaluate_output
from csr_core.scenario import read_scenario_meta
from csr_core.types import ElementType

pytestmark = pytest.mark.integration

CSR = [str(Path(sys.executable).parent / "csr")]


def _run(*args: str, check: bool = True) -> subprocess.CompletedProcess:
    proc = subprocess.run(CSR + list(args), capture_output=True, text=True, timeout=300)
    if check:
        assert proc.returncode == 0, proc.stderr[-2000:]
    return proc


@pytest.fixture(scope="module")
def scenario(tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("sim") / "urban"
    _run(
        "simulate",
        "--world",
        "urban",
        "--trips",
        "3",
        "--profile",
        "standard",
        "--seed",
        "7",
        "--out",
        str(out),
        "--trip-length-m",
        "500",
    )
    return out


@pytest.fixture(scope="module")
def outputs(scenario, tmp_path_factory) -> dict[str, Path]:
    root = tmp_path_factory.mktemp("recon")
    out = {}
    for method in ("pipeline", "gnss_only", "roadmap_icp"):
        out[method] = root / method
        proc = _run("reconstruct", str(scenario), "--out", str(out[method]), "--method", method)
        assert proc.stdout.strip().splitlines()[-1].startswith("csr reconstruct:")
    return out


def _upload(path: Path) -> dict:
    return orjson.loads(gzip.decompress(path.read_bytes()))


@pytest.mark.parametrize("method", ["pipeline", "gnss_only", "roadmap_icp"])
def test_outputs_follow_contract_section_4(scenario, outputs, method):
    out = outputs[method]
    trip_files = sorted((scenario / "trips").glob("*.json.gz"))
    csvs = sorted((out / "poses").glob("*.csv"))
    assert [p.name.removesuffix(".csv") for p in csvs] == [
        p.name.removesuffix(".json.gz") for p in trip_files
    ]
    for trip_file, csv in zip(trip_files, csvs, strict=False):
        doc = _upload(trip_file)
        lines = csv.read_text().splitlines()
        assert lines[0] == "t,lat,lon,heading_deg"
        rows = np.array([[float(v) for v in line.split(",")] for line in lines[1:]])
        assert rows.shape == (len(doc["frames"]), 4)
        np.testing.assert_allclose(rows[:, 0], [f["t"] for f in doc["frames"]], atol=1e-3)
        assert np.isfinite(rows).all()
        assert ((rows[:, 3] >= 0) & (rows[:, 3] < 360)).all()
    fc = orjson.loads((out / "map.geojson").read_bytes())
    assert fc["type"] == "FeatureCollection" and fc["features"]
    for feat in fc["features"]:
        etype = ElementType(feat["properties"]["type"])
        geom = feat["geometry"]
        if etype.is_polygon:
            assert geom["type"] == "Polygon" and geom["coordinates"][0][0] == geom["coordinates"][0][-1]
        else:
            assert geom["type"] == "LineString" and len(geom["coordinates"]) >= 2
    report = orjson.loads((out / "report.json").read_bytes())
    assert report["trips"] == len(trip_files) and report["method"] == method
    held = orjson.loads((out / "held_back.geojson").read_bytes())
    assert held["type"] == "FeatureCollection"
    assert all(f["properties"]["status"] == "held_back" for f in held["features"])
    if method == "pipeline":
        assert len(held["features"]) == report["diagnostics"]["held_back_features"]
        # trips with good GNSS: none marked degraded, none reverted after the alignment
        assert report["degraded"] == {} and report["diagnostics"]["alignment_reverted"] == {}


def test_gnss_only_accuracy_is_in_the_band_the_profile_implies(scenario, outputs):
    ev = evaluate_output(scenario, outputs["gnss_only"])
    e = ev.evaluation
    assert e.coverage == 1.0 and e.trips == 3
    gnss = read_scenario_meta(scenario).profile["gnss"]
    per_axis = [np.hypot(m["bias_sigma_m"], m["white_sigma_m"]) for m in gnss["status_models"]]
    speeds = [np.linalg.norm(np.diff(xy, axis=0), axis=1).max() * 10 for xy in ev.true_xy_by_key.values()]
    lower = np.sqrt(2) * min(per_axis)  # the best receiver state's 2-D error
    upper = 3 * (np.sqrt(2) * max(per_axis) + gnss.get("latency_mean_s", 0.0) * max(speeds))
    assert lower < e.aligned.ate.rmse < upper, (lower, e.aligned.ate.rmse, upper)
    assert e.aligned.ate.rmse <= e.raw.ate.rmse + 1e-9
    assert 0.0 < e.aligned.rpe.rmse < upper
    assert 0.0 < e.map_aligned.mcd < 1.0


def test_the_pipeline_equals_gnss_only_until_stages_are_wired_or_beats_it(scenario, outputs):
    pipe = evaluate_output(scenario, outputs["pipeline"]).evaluation
    gnss = evaluate_output(scenario, outputs["gnss_only"]).evaluation
    assert pipe.aligned.ate.rmse <= gnss.aligned.ate.rmse + 1e-6


def test_reconstruct_reads_only_the_trips(scenario, tmp_path):
    bare = tmp_path / "bare"
    shutil.copytree(scenario / "trips", bare / "trips")
    _run("reconstruct", str(bare), "--out", str(tmp_path / "out"), "--method", "gnss_only", "--no-progress")
    assert len(list((tmp_path / "out" / "poses").glob("*.csv"))) == 3


def test_a_missing_or_invalid_scenario_gives_a_clear_error(scenario, tmp_path):
    proc = _run("reconstruct", str(tmp_path / "nope"), "--out", str(tmp_path / "o1"), check=False)
    assert proc.returncode == 2 and "nope" in proc.stderr
    broken = tmp_path / "broken"
    shutil.copytree(scenario / "trips", broken / "trips")
    victim = sorted((broken / "trips").glob("*.json.gz"))[1]
    victim.write_bytes(gzip.compress(b'{"schema_version": "1.0"}'))
    proc = _run("reconstruct", str(broken), "--out", str(tmp_path / "o2"), check=False)
    assert proc.returncode == 2 and victim.name in proc.stderr
