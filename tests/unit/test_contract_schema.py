"""The vendored upload schema is the contract's, byte for byte, and the fast validator agrees with it."""

import json
import pathlib

import pytest

pytestmark = pytest.mark.unit

ROOT = pathlib.Path(__file__).resolve().parents[2]
SHARED_CONTRACT = ROOT.parent / "shared" / "contract"


def test_vendored_schema_is_the_contracts():
    vendored = (ROOT / "csr_core" / "schemas" / "trip-upload.schema.json").read_bytes()
    assert vendored == (SHARED_CONTRACT / "trip-upload.schema.json").read_bytes()


def test_contract_example_is_valid_for_both_validators():
    import jsonschema

    from csr_core.upload import decode_trip, validate_upload_json

    body = (SHARED_CONTRACT / "example-trip.json").read_bytes()
    schema = json.loads((SHARED_CONTRACT / "trip-upload.schema.json").read_text())
    jsonschema.Draft202012Validator(schema).validate(json.loads(body))
    trip = decode_trip(validate_upload_json(body))
    assert trip.n_frames == len(json.loads(body)["frames"])
