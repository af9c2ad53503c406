"""Keys and roles: bearer parsing, role checks, hashed storage, revocation."""

from __future__ import annotations

import pytest
from pydantic import TypeAdapter, ValidationError

from services.api.errors import ApiError
from services.api.routes.keys import KeyRequest
from services.auth import Caller, authenticate, authorize, bearer_secret, may_read_trip
from services.db import repo
from services.db.engine import make_engine, make_session_factory, migrate
from services.db.models import ApiKey

pytestmark = pytest.mark.unit


@pytest.fixture
def session_factory(tmp_path):
    engine = make_engine(f"sqlite:///{tmp_path / 'k.sqlite3'}")
    migrate(engine)
    yield make_session_factory(engine)
    engine.dispose()


@pytest.mark.parametrize("header", [None, "", "Bearer", "Bearer   ", "Basic abc", "token abc"])
def test_missing_or_malformed_authorization_is_401(header):
    with pytest.raises(ApiError) as caught:
        bearer_secret(header)
    assert caught.value.status == 401 and caught.value.headers == {"WWW-Authenticate": "Bearer"}


def test_bearer_scheme_is_case_insensitive():
    assert bearer_secret("bearer  abc ") == "abc"


def test_roles():
    reader = Caller("r", "reader", None)
    assert authorize(reader, ("reader", "admin")) is reader
    with pytest.raises(ApiError) as caught:
        authorize(reader, ("admin",))
    assert caught.value.status == 403
    vehicle = Caller("v", "vehicle", "veh-1")
    may_read_trip(vehicle, "veh-1")
    may_read_trip(reader, "veh-2")
    with pytest.raises(ApiError):
        may_read_trip(vehicle, "veh-2")


def test_keys_are_stored_hashed_and_revocation_is_immediate(session_factory):
    with session_factory.begin() as session:
        row, secret = repo.create_key(session, role="vehicle", vehicle_id="veh-1")
        key_id = row.id
    with session_factory() as session:
        stored = session.get(ApiKey, key_id)
        assert stored.key_sha256 == repo.hash_key(secret) and secret not in stored.key_sha256
    assert authenticate(session_factory, f"Bearer {secret}") == Caller(key_id, "vehicle", "veh-1")
    with session_factory.begin() as session:
        assert repo.revoke_key(session, key_id=key_id)
        assert not repo.revoke_key(session, key_id=key_id)
    with pytest.raises(ApiError) as caught:
        authenticate(session_factory, f"Bearer {secret}")
    assert caught.value.status == 401


def test_bootstrap_admin_key_is_replaced_when_it_changes(session_factory):
    for secret in ("first", "second"):
        with session_factory.begin() as session:
            repo.ensure_bootstrap_admin(session, secret=secret)
    assert authenticate(session_factory, "Bearer second").role == "admin"
    with pytest.raises(ApiError):
        authenticate(session_factory, "Bearer first")


@pytest.mark.parametrize(
    "body,ok",
    [
        ({"role": "vehicle", "vehicle_id": "veh-1"}, True),
        ({"role": "reader"}, True),
        ({"role": "admin"}, True),
        ({"role": "vehicle"}, False),
        ({"role": "reader", "vehicle_id": "veh-1"}, False),
        ({"role": "vehicle", "vehicle_id": "bad id"}, False),
        ({"role": "superuser"}, False),
        ({"role": "reader", "extra": 1}, False),
    ],
)
def test_key_request_validation(body, ok):
    adapter: TypeAdapter = TypeAdapter(KeyRequest)
    if ok:
        assert adapter.validate_python(body).role == body["role"]
    else:
        with pytest.raises(ValidationError):
            adapter.validate_python(body)
