"""Keyset pagination of listings: ``?limit=N&cursor=C``.

A page is the first ``limit`` rows after the cursor in the listing's stable order (its sort key
is unique within the listing, e.g. ends with the primary key, so no row is skipped or repeated
between pages, even while rows are added). The answer carries ``next``, the URL of the following page (``null`` on the last page),
which is also sent as a ``Link: <...>; rel="next"`` header (RFC 8288). A cursor is opaque to
clients: the base64url JSON of the last row's sort key. The query reads ``limit + 1`` rows to
know whether a next page exists, along an index that starts with the listing's filter columns
and ends with its sort key.
"""

from __future__ import annotations

import base64
import binascii
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Annotated, Any

import orjson
from fastapi import Query, Request
from fastapi.responses import Response
from sqlalchemy import ColumnExpressionArgument, Select, tuple_

from services.api.errors import ApiError
from services.api.params import fits_db_int, has_control_characters

DEFAULT_LIMIT = (
    1000  # a page holds all of the busiest tile seen (259 pairs): clients that do not page keep working
)
MAX_LIMIT = 5000

Limit = Annotated[int, Query(ge=1, le=MAX_LIMIT, description=f"rows per page (default {DEFAULT_LIMIT})")]
Cursor = Annotated[str | None, Query(description="the `next` cursor of the previous page (opaque)")]


@dataclass(frozen=True, slots=True)
class Page:
    rows: Sequence[Any]
    next_cursor: str | None  # None: this is the last page


def encode_cursor(key: Sequence[Any]) -> str:
    """The opaque cursor of a sort key (JSON scalars)."""
    return base64.urlsafe_b64encode(orjson.dumps(list(key))).decode().rstrip("=")


def decode_cursor(cursor: str, types: Sequence[type]) -> tuple[Any, ...]:
    """The sort key in ``cursor``, checked against the listing's key ``types``; 422 naming
    ``cursor`` when it is not a cursor of this listing."""
    try:
        key = orjson.loads(base64.urlsafe_b64decode(cursor + "=" * (-len(cursor) % 4)))
    except (binascii.Error, ValueError) as exc:
        raise _bad_cursor("not a cursor of this listing") from exc
    if not isinstance(key, list) or len(key) != len(types):
        raise _bad_cursor("not a cursor of this listing")
    out = []
    for value, kind in zip(key, types, strict=True):
        if kind is float and isinstance(value, int) and not isinstance(value, bool):
            value = float(value)
        if not isinstance(value, kind) or isinstance(value, bool) or not _storable(value):
            raise _bad_cursor("not a cursor of this listing")
        out.append(value)
    return tuple(out)


def _storable(value: Any) -> bool:
    """Whether both databases can compare ``value`` with a column (a sort key's type)."""
    if isinstance(value, int):
        return fits_db_int(value)
    if isinstance(value, str):
        return not has_control_characters(value)
    return True


def _bad_cursor(why: str) -> ApiError:
    return ApiError(422, "invalid_request", f"query.cursor: {why}", location="query.cursor")


def keyset_page(
    session: Any,
    stmt: Select,
    key: Sequence[ColumnExpressionArgument[Any]],
    *,
    limit: int,
    after: tuple[Any, ...] | None,
) -> Page:
    """The page of ``stmt`` (rows whose last ``len(key)`` columns are the sort key ``key``, unique
    within the listing) after the sort key ``after``."""
    if after is not None:
        stmt = stmt.where(tuple_(*key) > tuple_(*after))
    rows = session.execute(stmt.order_by(*key).limit(limit + 1)).all()
    if len(rows) <= limit:
        return Page(rows, None)
    rows = rows[:limit]
    return Page(rows, encode_cursor(tuple(rows[-1])[-len(key) :]))


def page_response(request: Request, body: dict[str, Any], page: Page) -> Response:
    """``body`` with ``next`` (the next page's URL or ``null``), and the ``Link`` header; encoded
    with orjson (a page of 1,000 pairs: ~5 ms, the standard library's encoder ~37 ms)."""
    next_url = str(request.url.include_query_params(cursor=page.next_cursor)) if page.next_cursor else None
    headers = {"Link": f'<{next_url}>; rel="next"'} if next_url else None
    content = orjson.dumps({**body, "next": next_url}, option=orjson.OPT_SERIALIZE_NUMPY)
    return Response(content, media_type="application/json", headers=headers)
