"""Accept-Encoding negotiation (RFC 9110 12.5.3), the codings' round trips and ETags per coding."""

from __future__ import annotations

import gzip

import brotli
import pytest
import zstandard

from services.api.content_coding import (
    Coding,
    Negotiated,
    compress,
    encoded_etag,
    identity_if_none_match,
    negotiate,
    requested_encoded,
)

pytestmark = pytest.mark.unit

IDENTITY = Negotiated(Coding.IDENTITY, True)


@pytest.mark.parametrize(
    ("header", "expected"),
    [
        (None, IDENTITY),
        ("", IDENTITY),
        ("gzip", Negotiated(Coding.GZIP, True)),
        ("GZIP", Negotiated(Coding.GZIP, True)),
        ("x-gzip", Negotiated(Coding.GZIP, True)),
        ("gzip, deflate, br, zstd", Negotiated(Coding.BR, True)),  # a tie: the server's order
        ("gzip, zstd", Negotiated(Coding.ZSTD, True)),
        ("br;q=0.5, gzip;q=0.9", Negotiated(Coding.GZIP, True)),
        ("br;q=0, gzip", Negotiated(Coding.GZIP, True)),
        ("br;q=0.5, identity", IDENTITY),  # identity weighs more
        ("br, identity;q=0.5", Negotiated(Coding.BR, True)),
        ("*", Negotiated(Coding.BR, True)),
        ("*;q=0.2, gzip", Negotiated(Coding.GZIP, True)),
        ("gzip, *;q=0", Negotiated(Coding.GZIP, False)),  # * covers identity
        ("gzip, identity;q=0", Negotiated(Coding.GZIP, False)),
        ("gzip, *;q=0, identity", Negotiated(Coding.GZIP, True)),
        ("compress, deflate", IDENTITY),  # nothing on offer: identity
        ("br;q=abc, gzip;q=2", IDENTITY),  # malformed weights are ignored
        (" gzip ; q=0.7 ,br;q=0.6", Negotiated(Coding.GZIP, True)),
        ("identity;q=0", None),
        ("*;q=0", None),
        ("compress, identity;q=0", None),
    ],
)
def test_negotiation(header: str | None, expected: Negotiated | None) -> None:
    assert negotiate(header) == expected


@pytest.mark.parametrize("coding", [Coding.BR, Coding.ZSTD, Coding.GZIP])
def test_codings_round_trip_and_are_deterministic(coding: Coding) -> None:
    body = b'{"type": "FeatureCollection", "features": []}' * 200
    packed = compress(body, coding)
    assert packed == compress(body, coding) and len(packed) < len(body) / 10
    unpack = {
        Coding.BR: brotli.decompress,
        Coding.GZIP: gzip.decompress,
        Coding.ZSTD: lambda raw: zstandard.ZstdDecompressor().decompressobj().decompress(raw),
    }[coding]
    assert unpack(packed) == body


def test_etags_per_coding() -> None:
    assert encoded_etag('"abc"', Coding.BR) == '"abc-br"'
    assert encoded_etag('W/"abc"', Coding.GZIP) == 'W/"abc-gzip"'
    assert encoded_etag('"abc"', Coding.IDENTITY) == '"abc"'
    # a coding's tags become identity tags; other codings' stay (they match nothing)
    header = '"abc-br", W/"def-br", "ghi-gzip", "plain"'
    assert identity_if_none_match(header, Coding.BR, identity_acceptable=True) == (
        '"abc", W/"def", "ghi-gzip", "plain"'
    )
    # identity not acceptable: the client's identity copy answers nothing
    assert (
        identity_if_none_match(header, Coding.BR, identity_acceptable=False) == '"abc", W/"def", "ghi-gzip"'
    )
    assert identity_if_none_match('"plain"', Coding.GZIP, identity_acceptable=False) is None
    assert identity_if_none_match("*", Coding.BR, identity_acceptable=True) == "*"
    # which representation a 304 names
    assert requested_encoded('"x", W/"abc-br"', '"abc"', Coding.BR)
    assert not requested_encoded('"abc"', '"abc"', Coding.BR)
    assert not requested_encoded('"abc-gzip"', '"abc"', Coding.BR)


def test_bench_http_measures_every_coding() -> None:
    from services.cli.bench_http import measure, section

    body = b'{"type": "Feature", "geometry": {"coordinates": [[8.4012345, 49.0123456]]}}' * 100
    rows = measure({"a body": body}, repeat=2)
    assert rows[0]["identity"] == len(body)
    for coding in (Coding.BR, Coding.ZSTD, Coding.GZIP):
        assert rows[0][coding.value][0] == len(compress(body, coding)) and rows[0][coding.value][1] >= 0
    table = section(rows, "karlsruhe", 2)
    assert f"| a body | {len(body):,} | {len(compress(body, Coding.BR)):,} (" in table
