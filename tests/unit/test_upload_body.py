"""Body limits: while streaming (as sent) and while decompressing (zip bombs), with memory bounded."""

from __future__ import annotations

import asyncio
import gzip
import tracemalloc
import zlib

import pytest

from services.api.body import OUTPUT_STEP_BYTES, gunzip_limited, read_limited
from services.api.errors import ApiError
from services.upload_budget import UploadBudget, reservation

pytestmark = pytest.mark.unit

MIB = 1024 * 1024


def _bomb(inflated_mib: int) -> bytes:
    compressor = zlib.compressobj(9, zlib.DEFLATED, 16 + zlib.MAX_WBITS)
    return b"".join(compressor.compress(b"\0" * MIB) for _ in range(inflated_mib)) + compressor.flush()


def test_gunzip_round_trip_and_multi_member():
    data = b'{"a": 1}' * 1000
    assert gunzip_limited(gzip.compress(data), max_bytes=len(data)) == data
    two = gzip.compress(data[:100]) + gzip.compress(data[100:])
    assert gunzip_limited(two, max_bytes=len(data)) == data


def test_gunzip_at_the_limit_passes_one_byte_over_is_413():
    data = b"x" * 5000
    assert len(gunzip_limited(gzip.compress(data), max_bytes=5000)) == 5000
    with pytest.raises(ApiError) as caught:
        gunzip_limited(gzip.compress(data), max_bytes=4999)
    assert caught.value.status == 413 and "after decompression" in caught.value.message


def test_zip_bomb_is_413_with_memory_bounded_by_the_limit():
    bomb = _bomb(200)  # 200 MiB inflated, ~200 KiB sent
    tracemalloc.start()
    try:
        with pytest.raises(ApiError) as caught:
            gunzip_limited(bomb, max_bytes=4 * MIB)
        _, peak = tracemalloc.get_traced_memory()
    finally:
        tracemalloc.stop()
    assert caught.value.status == 413
    assert peak < 3 * 4 * MIB  # a small multiple of the limit (output + one chunk), never the 200 MiB


@pytest.mark.parametrize(
    "body", [b"not gzip", gzip.compress(b"{}" * 5000)[:40], gzip.compress(b"{}") + b"trailing"]
)
def test_malformed_or_truncated_gzip_is_400(body):
    with pytest.raises(ApiError) as caught:
        gunzip_limited(body, max_bytes=MIB)
    assert caught.value.status == 400 and caught.value.error == "gzip"


def test_streaming_read_stops_past_the_limit_without_reading_the_rest():
    consumed = 0

    async def endless():
        nonlocal consumed
        while True:
            consumed += 1
            yield b"y" * 1000

    with pytest.raises(ApiError) as caught:
        asyncio.run(read_limited(endless(), max_bytes=10_500))
    assert caught.value.status == 413 and "as sent" in caught.value.message
    assert consumed == 11


def test_streaming_read_collects_a_body_within_the_limit():
    async def chunks():
        for part in (b"ab", b"cd", b"e"):
            yield part

    assert asyncio.run(read_limited(chunks(), max_bytes=5)) == b"abcde"


def test_a_zip_bomb_never_holds_more_than_the_limit_and_one_step():
    limit = 16 * MIB
    bomb = _bomb(64)
    tracemalloc.start()
    try:
        with pytest.raises(ApiError) as caught:
            gunzip_limited(bomb, max_bytes=limit)
        _, peak = tracemalloc.get_traced_memory()
    finally:
        tracemalloc.stop()
    assert caught.value.status == 413
    # the output (with its growth margin) and one step; inflating to the limit in one call holds it twice
    assert peak < 1.3 * limit


def test_inflation_reserves_each_step_before_keeping_it_and_stops_when_refused():
    data = bytes(range(256)) * (3 * OUTPUT_STEP_BYTES // 256 + 7)
    steps: list[int] = []
    assert gunzip_limited(gzip.compress(data), max_bytes=len(data), reserve=steps.append) == data
    assert sum(steps) == len(data) and max(steps) <= OUTPUT_STEP_BYTES

    def refuse_past_two_mib(n_bytes: int) -> None:
        steps.append(n_bytes)
        if sum(steps) > 2 * MIB:
            raise ApiError(503, "busy", "full")

    steps.clear()
    with pytest.raises(ApiError) as caught:
        gunzip_limited(_bomb(64), max_bytes=256 * MIB, reserve=refuse_past_two_mib)
    assert caught.value.status == 503 and sum(steps) <= 2 * MIB + OUTPUT_STEP_BYTES


def test_the_budget_refuses_what_does_not_fit_with_503_and_retry_after():
    budget = UploadBudget(10 * MIB)
    with reservation(budget) as first:
        first.grow(6 * MIB)
        with reservation(budget) as second, pytest.raises(ApiError) as caught:
            second.grow(2 * MIB)
            second.grow(3 * MIB)
        assert budget.used_bytes == 6 * MIB  # the refused one gave back what it held
        error = caught.value
        assert (error.status, error.error, error.location) == (503, "busy", "body")
        assert int(error.headers["Retry-After"]) > 0 and str(10 * MIB) in error.message
    assert budget.used_bytes == 0


def test_a_budget_below_the_decompressed_limit_is_refused_at_start():
    from pydantic import ValidationError

    from services.settings import Settings

    with pytest.raises(ValidationError, match="CSR_MAX_UPLOAD_BYTES_IN_FLIGHT"):
        Settings(max_decompressed_bytes=8 * MIB, max_upload_bytes_in_flight=4 * MIB)
    assert (
        Settings(max_decompressed_bytes=8 * MIB, max_upload_bytes_in_flight=8 * MIB).max_frames_per_trip > 0
    )
