"""The request checks shared by every route: integer bounds, control characters, Cache-Control."""

from __future__ import annotations

import pytest

from services.api.errors import ApiError
from services.api.params import DB_INT_MAX, DB_INT_MIN, check_int, has_control_characters
from services.tiles.http import cache_control

pytestmark = pytest.mark.unit


@pytest.mark.parametrize("raw", [str(DB_INT_MAX + 1), str(DB_INT_MIN - 1), "9223372036854775808", "1" * 40])
def test_integers_past_the_databases_columns_are_422_naming_the_parameter(raw: str) -> None:
    with pytest.raises(ApiError) as caught:
        check_int("query.since", raw)
    assert (caught.value.status, caught.value.location) == (422, "query.since")


@pytest.mark.parametrize(
    ("raw", "value"), [(str(DB_INT_MAX), DB_INT_MAX), ("-7", -7), ("abc", None), ("1.5", None)]
)
def test_integers_in_range_pass_and_non_integers_are_left_to_the_route(raw: str, value: int | None) -> None:
    assert check_int("path.v", raw) == value


@pytest.mark.parametrize(
    ("text", "bad"), [("a\x00b", True), ("\n", True), ("\x7f", True), ("trip-1:x.y", False)]
)
def test_control_characters(text: str, bad: bool) -> None:
    assert has_control_characters(text) is bad


def test_map_answers_are_private_unless_the_map_is_public() -> None:
    assert cache_control(pinned=False, public_map=False) == "private, max-age=30"
    assert cache_control(pinned=True, public_map=False) == "private, max-age=31536000, immutable"
    assert cache_control(pinned=False, public_map=True) == "public, max-age=30"
    assert cache_control(pinned=True, public_map=True) == "public, max-age=31536000, immutable"
