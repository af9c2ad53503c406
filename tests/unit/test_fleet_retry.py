"""The fleet's client sends a call again after a 503's ``Retry-After``, a bounded number of times."""

from __future__ import annotations

import httpx
import pytest

from services.fleet import BUSY_ATTEMPTS, RetryBusy

pytestmark = pytest.mark.unit


def _client(answers: list[int], calls: list[bytes]) -> httpx.Client:
    def answer(request: httpx.Request) -> httpx.Response:
        calls.append(request.read())
        status = answers.pop(0) if answers else 503
        return httpx.Response(status, headers={"Retry-After": "0"}, json={})

    return httpx.Client(base_url="http://csr", transport=RetryBusy(httpx.MockTransport(answer)))


def test_a_busy_answer_is_retried_with_the_same_body() -> None:
    calls: list[bytes] = []
    with _client([503, 503, 202], calls) as http:
        assert http.post("/v1/trips", content=b'{"trip": 1}').status_code == 202
    assert calls == [b'{"trip": 1}'] * 3


def test_retries_are_bounded() -> None:
    calls: list[bytes] = []
    with _client([], calls) as http:
        assert http.get("/v1/jobs/summary").status_code == 503
    assert len(calls) == BUSY_ATTEMPTS
