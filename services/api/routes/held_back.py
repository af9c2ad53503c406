"""Lines held back from a tile version, for the map team to confirm or correct (docs/tiles.md,
"Held-back lines").

- ``GET /v1/tiles/{z}/{x}/{y}/held-back[?version=N]``   the held-back lines of the tile's latest
  version (or of version N) as GeoJSON, each with ``"status": "held_back"``

The merge holds back a line that several trips drove alongside without seeing it (a ghost, a
mis-spliced line: ``TopologyResult.suppressed``). The version's ``quality["held_back"]`` counts them
by type; their geometry lives only in the version's topology state, which this route unpickles and
clips to the tile as the merge did, so the features here are exactly the ones counted there.

A version without a readable state (written without one, or by an older algorithm) is a 409
``state_unavailable``, not an empty collection: "nothing was held back" and "we cannot tell" must
not look alike to a client.
"""

from __future__ import annotations

from typing import Annotated

from fastapi import APIRouter, Query
from fastapi.responses import Response

from services.api import answers
from services.api.deps import Ctx, Reader, ReadSessionDep
from services.api.errors import ApiError
from services.api.openapi import errors
from services.api.routes.versions import version_or_404
from services.db import versions as vs
from services.tiles.http import CORS_HEADERS, cache_control, check_tile
from services.tiles.render import feature_collection, feature_json

router = APIRouter(prefix="/v1", tags=["versions"])

HELD_BACK_STATUS = "held_back"  # each feature's ``status``: not in the published map


@router.get(
    "/tiles/{z}/{x}/{y}/held-back",
    response_class=Response,
    responses={
        200: answers.geojson("The held-back lines, with `tile`, `version` and `map_version`"),
        **errors(
            {
                404: {"not_found": "the tile has no versions, or not this one."},
                409: {"state_unavailable": "the version has no readable topology state."},
            }
        ),
    },
)
def held_back_lines(
    _: Reader,
    ctx: Ctx,
    session: ReadSessionDep,
    z: int,
    x: int,
    y: int,
    version: Annotated[int | None, Query(ge=1, description="tile version (default: the latest)")] = None,
) -> Response:
    """The lines held back from the tile's latest version (or ``version``) as a GeoJSON
    FeatureCollection with ``tile``, ``version`` and ``map_version``; per feature the properties the
    merge gave it and ``"status": "held_back"``. 409 when the version has no readable topology state."""
    # the job code (and the topology types the state unpickles to) is loaded at the first call
    # only, as app.py loads the job runners: routes do not import workers/ at module level
    from workers.tile_jobs import held_back_features

    with session.begin():
        check_tile(z, x, y)
        row = version_or_404(session, z, x, y, version, "query.version")
        held = held_back_features(row)
        if held is None:
            raise ApiError(
                409,
                "state_unavailable",
                f"tile {z}/{x}/{y} v{row.version} has no readable topology state (written without one, or "
                "by an older algorithm): its held-back lines are unknown",
                location="query.version" if version is not None else "path",
            )
        mapped = [vs.MapFeature(f, row.id, z, x, y, row.version) for f in held]
        body = feature_collection(
            [feature_json(m, extra={"status": HELD_BACK_STATUS}) for m in mapped],
            tile=f"{z}/{x}/{y}",
            version=row.version,
            map_version=row.id,
        )
    # a pinned version never changes; the latest does when the tile is merged again
    cache = cache_control(pinned=version is not None, public_map=ctx.settings.public_map)
    return Response(body, media_type="application/geo+json", headers={**CORS_HEADERS, "Cache-Control": cache})
