"""The vendored upload schema and example are the contract's, byte for byte, and the fast validator
agrees with the schema.

The contract lives in ``../shared/contract`` beside a checkout. Where that folder exists, the
vendored copies (``csr_core/schemas/trip-upload.schema.json``, ``tests/data/example-trip.json``)
are compared with it; where it does not (a fresh clone), the comparison has nothing to compare
against and the vendored copies stand for the contract in the validator test.
"""

import json
import pathlib

import pytest

pytestmark = pytest.mark.unit

ROOT = pathlib.Path(__file__).resolve().parents[2]
SHARED_CONTRACT = ROOT.parent / "shared" / "contract"
VENDORED_SCHEMA = ROOT / "csr_core" / "schemas" / "trip-upload.schema.json"
VENDORED_EXAMPLE = ROOT / "tests" / "data" / "example-trip.json"


def _contract(name: str, vendored: pathlib.Path) -> pathlib.Path:
    """The contract's file, or the vendored copy where ``../shared`` is absent."""
    shared = SHARED_CONTRACT / name
    return shared if shared.exists() else vendored


def test_vendored_schema_and_example_are_the_contracts():
    assert VENDORED_SCHEMA.read_bytes() == _contract("trip-upload.schema.json", VENDORED_SCHEMA).read_bytes()
    assert VENDORED_EXAMPLE.read_bytes() == _contract("example-trip.json", VENDORED_EXAMPLE).read_bytes()


def test_contract_example_is_valid_for_both_validators():
    import jsonschema

    from csr_core.upload import decode_trip, validate_upload_json

    body = _contract("example-trip.json", VENDORED_EXAMPLE).read_bytes()
    schema = json.loads(_contract("trip-upload.schema.json", VENDORED_SCHEMA).read_text())
    jsonschema.Draft202012Validator(schema).validate(json.loads(body))
    trip = decode_trip(validate_upload_json(body))
    assert trip.n_frames == len(json.loads(body)["frames"])
