"""``DELETE /v1/vehicles/{vehicle_id}/data`` (admin): erase a vehicle's trips and everything keyed by
them, then re-merge the tiles they touched into new map versions without them (``services.erasure``).
``?dry_run=true`` answers what would go and changes nothing. A second call answers ``"trips": 0``."""

from __future__ import annotations

import re
from typing import Annotated, Any

from fastapi import APIRouter, Path, Query

from services.api.deps import Admin, Ctx, SessionDep
from services.api.errors import ApiError
from services.api.openapi import errors
from services.erasure import ErasurePlan, erase_vehicle, plan_vehicle_erasure

router = APIRouter(prefix="/v1/vehicles", tags=["vehicles"])

VEHICLE_ID = re.compile(r"^[A-Za-z0-9._:-]{1,64}$")  # trip-upload.schema.json's vehicle_id


def _tiles(plan: ErasurePlan) -> list[str]:
    return [f"{z}/{x}/{y}" for z, x, y in plan.tiles]


@router.delete(
    "/{vehicle_id}/data",
    responses={
        200: {
            "description": "What was erased (`trips`, `trip_ids`), or with `dry_run` what would be and "
            "the tiles re-merged; a second call answers `trips: 0`",
            "content": {"application/json": {"schema": {"type": "object"}}},
        },
        **errors({422: {"invalid_request": "a `vehicle_id` the upload schema would refuse."}}),
    },
)
def erase_vehicle_data(
    vehicle_id: Annotated[
        str, Path(description="the uploads' `vehicle_id`", json_schema_extra={"pattern": VEHICLE_ID.pattern})
    ],
    _: Admin,
    ctx: Ctx,
    session: SessionDep,
    dry_run: Annotated[bool, Query(description="answer what would be erased; change nothing")] = False,
) -> dict[str, Any]:
    if not VEHICLE_ID.fullmatch(vehicle_id):
        raise ApiError(
            422,
            "invalid_request",
            "vehicle_id must be 1-64 characters of A-Z a-z 0-9 . _ : - (as in uploads)",
            location="path.vehicle_id",
        )
    if dry_run:
        with session.begin():
            plan = plan_vehicle_erasure(session, vehicle_id=vehicle_id)
        return {
            "vehicle_id": vehicle_id,
            "dry_run": True,
            "trips": len(plan.trip_pks),
            "trip_ids": plan.trip_pks,
            "tiles": _tiles(plan),
            "merge_jobs": [],
        }
    with session.begin():
        plan = plan_vehicle_erasure(session, vehicle_id=vehicle_id)
        result = erase_vehicle(session, plan=plan)
    if result.merge_jobs:
        ctx.runner.wake()
    return {
        "vehicle_id": vehicle_id,
        "dry_run": False,
        "trips": result.trips,
        "trip_ids": plan.trip_pks,
        "tiles": _tiles(plan),
        "match_pairs": result.match_pairs,
        "versions_rewritten": result.versions_rewritten,
        "merge_jobs": result.merge_jobs,
    }
