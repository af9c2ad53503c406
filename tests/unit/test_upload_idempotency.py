"""Idempotency of ``accept_upload`` (services.uploads) on the embedded SQLite store: same content
is a replay, other content a conflict, concurrent identical uploads make one trip, and a rejected
upload writes nothing."""

from __future__ import annotations

import gzip
import json
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import pytest
from sqlalchemy import func, select

from csr_core.errors import UploadError
from services.api.errors import ApiError
from services.auth import Caller
from services.db.engine import make_engine, make_session_factory, migrate
from services.db.models import Job, Trip, TripUpload
from services.settings import Settings
from services.uploads import accept_upload

pytestmark = pytest.mark.unit

EXAMPLE = (Path(__file__).resolve().parents[2] / "tests" / "data" / "example-trip.json").read_bytes()
ADMIN = Caller(key_id="k", role="admin", vehicle_id=None)


@pytest.fixture
def store(tmp_path):
    settings = Settings(data_dir=tmp_path, _env_file=None)
    engine = make_engine(settings.sqlalchemy_url)
    migrate(engine)
    yield settings, make_session_factory(engine)
    engine.dispose()


def _accept(store, body: bytes, *, caller: Caller = ADMIN, gzipped: bool = False):
    settings, session_factory = store
    return accept_upload(
        session_factory=session_factory, settings=settings, caller=caller, body=body, gzipped=gzipped
    )


def _counts(store) -> tuple[int, int, int]:
    with store[1]() as session:
        return tuple(session.scalar(select(func.count()).select_from(t)) for t in (Trip, TripUpload, Job))


def test_same_content_is_a_replay_with_the_same_id(store):
    first = _accept(store, EXAMPLE)
    again = _accept(store, gzip.compress(EXAMPLE), gzipped=True)
    sniffed = _accept(store, gzip.compress(EXAMPLE))  # gzip without the header is recognised
    assert first.created and not again.created and not sniffed.created
    assert first.trip.id == again.trip.id == sniffed.trip.id
    assert _counts(store) == (1, 1, 1)


def test_other_content_under_the_same_key_is_409_and_changes_nothing(store):
    _accept(store, EXAMPLE)
    doc = json.loads(EXAMPLE)
    doc["frames"][0]["odom"]["x"] = 0.5
    with pytest.raises(ApiError) as caught:
        _accept(store, json.dumps(doc).encode())
    assert caught.value.status == 409
    assert _counts(store) == (1, 1, 1)


def test_concurrent_identical_uploads_make_one_trip(store):
    with ThreadPoolExecutor(10) as pool:
        results = list(pool.map(lambda _: _accept(store, EXAMPLE), range(10)))
    assert sum(r.created for r in results) == 1
    assert len({r.trip.id for r in results}) == 1
    assert _counts(store) == (1, 1, 1)


def test_rejected_upload_writes_nothing(store):
    doc = json.loads(EXAMPLE)
    doc["frames"][2]["t"] = 0.0
    with pytest.raises(UploadError):
        _accept(store, json.dumps(doc).encode())
    assert _counts(store) == (0, 0, 0)


def test_vehicle_key_is_bound_to_its_vehicle(store):
    other = Caller(key_id="v", role="vehicle", vehicle_id="someone-else")
    with pytest.raises(ApiError) as caught:
        _accept(store, EXAMPLE, caller=other)
    assert caught.value.status == 403
    own = Caller(key_id="v", role="vehicle", vehicle_id=json.loads(EXAMPLE)["vehicle_id"])
    assert _accept(store, EXAMPLE, caller=own).created
