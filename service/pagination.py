"""Keyset pagination of the listing routes: an opaque cursor naming the last row of a page.

A cursor is the ``(created_at, id)`` of the last item shown, base64url-encoded JSON; the next
page is what was created before it (newest first), so pages neither skip nor repeat items
while others are added or deleted.
"""

from __future__ import annotations

import base64
import binascii
import json
import math
from typing import Annotated

from fastapi import Query

from jobs.store import MAX_PAGE
from service.errors import ApiError

LimitQuery = Annotated[int, Query(ge=1, le=MAX_PAGE, description=f"items per page (at most {MAX_PAGE})")]
CursorQuery = Annotated[str | None, Query(max_length=200, description="next_cursor of the previous page")]


def encode_cursor(row: dict) -> str:
    raw = json.dumps([row["created_at"], row["id"]], separators=(",", ":")).encode()
    return base64.urlsafe_b64encode(raw).decode().rstrip("=")


def decode_cursor(cursor: str | None) -> tuple[float, str] | None:
    if cursor is None:
        return None
    try:
        raw = base64.urlsafe_b64decode(cursor + "=" * (-len(cursor) % 4))
        created_at, row_id = json.loads(raw)
        if not (isinstance(created_at, (int, float)) and math.isfinite(created_at) and isinstance(row_id, str)):
            raise ValueError
    except (binascii.Error, ValueError, TypeError, UnicodeDecodeError):
        raise ApiError(400, "invalid_cursor", "cursor: not a next_cursor value of this API") from None
    return float(created_at), row_id


def page(rows: list[dict], limit: int) -> tuple[list[dict], str | None]:
    """``rows`` fetched with ``limit + 1``: the page and the cursor of the next one (or None)."""
    if len(rows) > limit:
        rows = rows[:limit]
        return rows, encode_cursor(rows[-1])
    return rows, None
