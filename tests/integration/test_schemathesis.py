"""The service answers as its OpenAPI document says, on both deployments: schemathesis (its CLI, every
check, every phase) runs against ``/openapi.json`` with an admin, a reader and a vehicle key, the
upload body included. No answer is a 5xx and no check fails; the only failures dropped are those
``tests/integration/schemathesis_hooks.py`` lists, each a rule JSON Schema cannot state. Beside it,
the answers schemathesis found at odds with the document, each pinned down."""

from __future__ import annotations

import collections
import os
import subprocess
import sys
from pathlib import Path

import httpx
import orjson
import pytest

from tests.integration.conftest import REPO, Deployment
from tests.openapi_check import response_schema

pytestmark = pytest.mark.integration

SCHEMATHESIS = Path(sys.executable).parent / "schemathesis"
# Test cases per operation and phase: about a minute per role on a quiet 2-core machine
MAX_EXAMPLES = 8
SEED = 20261203


@pytest.fixture(params=["embedded", "distributed"])
def running(request, make_isolated) -> Deployment:
    """A deployment of its own (schemathesis creates keys, trips and corrections in it)."""
    if request.param == "distributed":
        dep = make_isolated("distributed", redis_url=request.getfixturevalue("private_redis").url)
        dep.start_server()
        dep.start_worker()
    else:
        dep = make_isolated("embedded")
        dep.start_server()
    return dep


def _keys(dep: Deployment) -> dict[str, str]:
    with dep.admin() as http:
        vehicle = http.post("/v1/keys", json={"role": "vehicle", "vehicle_id": "veh-st"})
        reader = http.post("/v1/keys", json={"role": "reader"})
    assert (vehicle.status_code, reader.status_code) == (201, 201), (vehicle.text, reader.text)
    return {"admin": dep.admin_key, "reader": reader.json()["key"], "vehicle": vehicle.json()["key"]}


def run_schemathesis(dep: Deployment, key: str, har: Path) -> subprocess.CompletedProcess[str]:
    """``schemathesis run`` with every check against ``dep`` as ``key``; its requests in ``har``."""
    env = {
        **os.environ,
        "SCHEMATHESIS_HOOKS": "tests.integration.schemathesis_hooks",
        "PYTHONPATH": os.pathsep.join(filter(None, [str(REPO), os.environ.get("PYTHONPATH")])),
    }
    command = [
        str(SCHEMATHESIS),
        "run",
        f"{dep.base_url}/openapi.json",
        "--checks",
        "all",
        "--header",
        f"Authorization: Bearer {key}",
        "--max-examples",
        str(MAX_EXAMPLES),
        "--seed",
        str(SEED),
        "--workers",
        "1",
        "--generation-database",
        "none",
        "--no-color",
        "--report",
        "har",
        "--report-har-path",
        str(har),
    ]
    return subprocess.run(command, capture_output=True, text=True, env=env, cwd=REPO, timeout=600)


def har_statuses(har: Path) -> collections.Counter[int]:
    entries = orjson.loads(har.read_bytes())["log"]["entries"]
    return collections.Counter(entry["response"]["status"] for entry in entries)


def test_schemathesis_finds_no_5xx_and_no_failure(running: Deployment, tmp_path: Path):
    for role, key in _keys(running).items():
        har = tmp_path / f"{role}.har"
        run = run_schemathesis(running, key, har)
        statuses = har_statuses(har)
        assert sum(statuses.values()) > 500, (role, statuses)  # every operation, every phase
        assert not [s for s in statuses if s >= 500], (role, statuses, run.stdout[-6000:])
        assert run.returncode == 0, (role, run.stdout[-12000:], run.stderr[-2000:])


# --- what schemathesis found, each answer as the document says -----------------------------------


def test_a_405_names_every_method_of_the_path(deployment: Deployment, served_doc):
    """``GET`` and ``POST /v1/trips`` are two routes: the 405's ``Allow`` names both."""
    with deployment.admin() as http:
        response = http.put("/v1/trips")
    assert response.status_code == 405
    documented = {m.upper() for m in served_doc["paths"]["/v1/trips"]}
    assert set(response.headers["allow"].split(", ")) == documented == {"GET", "POST"}


def test_a_body_that_is_not_text_is_400_json(deployment: Deployment, served_doc):
    with deployment.admin() as http:
        response = http.post("/v1/keys", content=b"\xff\xfe{", headers={"Content-Type": "application/json"})
    assert response.status_code == 400, response.text
    assert response.json()["error"] == "json" and response.json()["location"] == "body"
    check = response_schema(served_doc, "POST", "/v1/keys", 400)
    assert sorted(e.message for e in check.iter_errors(response.json())) == []


def test_a_key_body_has_the_fields_of_its_role(deployment: Deployment):
    with deployment.admin() as http:
        reader_with_vehicle = http.post("/v1/keys", json={"role": "reader", "vehicle_id": "veh-1"})
        vehicle_without = http.post("/v1/keys", json={"role": "vehicle"})
        admin = http.post("/v1/keys", json={"role": "admin", "vehicle_id": None})
    assert reader_with_vehicle.status_code == 422
    assert reader_with_vehicle.json()["location"].endswith("vehicle_id"), reader_with_vehicle.json()
    assert vehicle_without.status_code == 422
    assert vehicle_without.json()["location"].endswith("vehicle_id"), vehicle_without.json()
    assert admin.status_code == 201 and admin.json()["vehicle_id"] is None


@pytest.fixture
def served_doc(deployment: Deployment) -> dict:
    return httpx.get(deployment.base_url + "/openapi.json").json()
