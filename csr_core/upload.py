"""Trip upload (contract section 1): validation and decoding into :class:`csr_core.types.Trip`.

Validation is the contract's JSON Schema (``schemas/trip-upload.schema.json``, a verbatim copy
of ``shared/contract``; a test checks they are identical) expressed as a pydantic model, so the
whole check runs in pydantic-core (Rust) straight from the JSON bytes: tens of times faster
than a pure-Python JSON Schema validator on a 30 MB trip. ``tests/unit/test_upload.py`` checks
the two agree on the example and on every kind of violation. On top of the schema: numbers must
be finite and ``t`` strictly increasing.
"""

from __future__ import annotations

import math
import re
from datetime import date
from typing import Annotated, Any, Literal, NotRequired, cast

import numpy as np
from annotated_types import Ge, Gt, Le, Len, Lt
from pydantic import ConfigDict, StringConstraints, TypeAdapter, ValidationError, with_config
from typing_extensions import TypedDict

from csr_core.errors import UploadError
from csr_core.types import DividerStyle, ElementType, GnssStatus, PerceivedElement, Trip

SCHEMA_VERSION = "1.0"
_CONFIG = ConfigDict(extra="forbid", strict=True, allow_inf_nan=False)

# RFC 3339 date-time (JSON Schema "format": "date-time"); at most 9 fraction digits keep it
# within the 40 characters the trips table stores. ``\Z``: no trailing newline.
_RFC3339 = re.compile(
    r"(?P<year>[0-9]{4})-(?P<month>[0-9]{2})-(?P<day>[0-9]{2})[Tt]"
    r"(?P<hour>[0-9]{2}):(?P<minute>[0-9]{2}):(?P<second>[0-9]{2})(\.[0-9]{1,9})?"
    r"([Zz]|[+-](?P<offset_hour>[0-9]{2}):(?P<offset_minute>[0-9]{2}))\Z"
)


@with_config(_CONFIG)
class _Gnss(TypedDict):
    lat: Annotated[float, Ge(-90), Le(90)]
    lon: Annotated[float, Ge(-180), Le(180)]
    status: Literal["rtk_fixed", "rtk_float", "dgps", "single", "none"]
    heading_deg: NotRequired[Annotated[float, Ge(0), Lt(360)]]
    std_m: NotRequired[Annotated[float, Gt(0)]]


@with_config(_CONFIG)
class _Odom(TypedDict):
    x: float
    y: float
    yaw: float


@with_config(_CONFIG)
class _Element(TypedDict):
    type: Literal["lane_divider", "road_boundary", "centerline", "stop_line", "crosswalk", "road_marking"]
    points: Annotated[list[Annotated[list[float], Len(2, 2)]], Len(2, 200)]
    style: NotRequired[Literal["solid", "dashed", "double", "unknown"]]
    score: NotRequired[Annotated[float, Ge(0), Le(1)]]
    track_id: NotRequired[int]


@with_config(_CONFIG)
class _Frame(TypedDict):
    t: Annotated[float, Ge(0)]
    gnss: _Gnss
    odom: _Odom
    elements: list[_Element]


@with_config(_CONFIG)
class _TripUpload(TypedDict):
    schema_version: str
    vehicle_id: Annotated[str, StringConstraints(pattern=r"^[A-Za-z0-9._:-]{1,64}$")]
    trip_id: Annotated[str, StringConstraints(pattern=r"^[A-Za-z0-9._:-]{1,128}$")]
    started_at: str
    sensor_setup: NotRequired[dict[str, Any]]
    frames: Annotated[list[_Frame], Len(2)]


_ADAPTER = TypeAdapter(_TripUpload)


def _json_path(loc: tuple[Any, ...]) -> str:
    out = ""
    for part in loc:
        if isinstance(part, int):
            out += f"[{part}]"
        else:
            out += ("." if out else "") + str(part)
    return out


def _error_from_pydantic(exc: ValidationError) -> UploadError:
    err = exc.errors(include_url=False)[0]
    loc = tuple(p for p in err["loc"] if not (isinstance(p, str) and p.startswith("function-")))
    path = _json_path(loc)
    kind = err["type"]
    if kind == "json_invalid":
        return UploadError(f"malformed JSON: {err['msg']}", location=path, reason="json")
    if loc == ("schema_version",) and kind != "missing":
        return UploadError(
            f"schema_version: unknown schema version ({err['msg']}); this server accepts {SCHEMA_VERSION!r}",
            location="schema_version",
            reason="version",
        )
    if kind == "finite_number":
        return UploadError(f"{path or 'value'}: number must be finite", location=path, reason="non_finite")
    where = f"{path}: " if path else ""
    if len(loc) >= 2 and loc[0] == "frames" and isinstance(loc[1], int):
        where = f"frame {loc[1]}, field {_json_path(loc[2:]) or '(frame)'}: "
    return UploadError(f"{where}{err['msg']}", location=path, reason="schema")


def _check_version(doc_head: Any) -> None:
    if isinstance(doc_head, dict) and "schema_version" in doc_head:
        version = doc_head["schema_version"]
        if version != SCHEMA_VERSION:
            raise UploadError(
                f"unknown schema_version {version!r}; this server accepts {SCHEMA_VERSION!r}",
                location="schema_version",
                reason="version",
            )


def is_rfc3339_date_time(text: str) -> bool:
    """Whether ``text`` is an RFC 3339 ``date-time``: the grammar and a real calendar date, hours
    0-23, minutes 0-59, seconds 0-60 (a leap second), an offset of at most 23:59."""
    match = _RFC3339.match(text)
    if match is None:
        return False
    part = {k: int(v) for k, v in match.groupdict(default="0").items()}
    try:
        date(part["year"], part["month"], part["day"])
    except ValueError:
        return False
    return (
        part["hour"] <= 23
        and part["minute"] <= 59
        and part["second"] <= 60
        and part["offset_hour"] <= 23
        and part["offset_minute"] <= 59
    )


def first_non_finite(value: Any, path: str) -> str | None:
    """The JSON path of the first NaN or infinite number in a parsed JSON value, or ``None``."""
    if isinstance(value, float):
        return None if math.isfinite(value) else path
    if isinstance(value, dict):
        items: Any = ((f"{path}.{key}", item) for key, item in value.items())
    elif isinstance(value, list):
        items = ((f"{path}[{i}]", item) for i, item in enumerate(value))
    else:
        return None
    for item_path, item in items:
        found = first_non_finite(item, item_path)
        if found is not None:
            return found
    return None


def _frame_times_s(doc: dict[str, Any]) -> np.ndarray:
    return np.fromiter((f["t"] for f in doc["frames"]), float, len(doc["frames"]))


def _check_semantics(doc: dict[str, Any], times_s: np.ndarray) -> None:
    """The checks beyond the schema: ``started_at``, finite ``sensor_setup``, ``t`` (``times_s``) increasing."""
    if not is_rfc3339_date_time(doc["started_at"]):
        raise UploadError(
            f"started_at: {doc['started_at']!r} is not an RFC 3339 date-time",
            location="started_at",
            reason="schema",
        )
    # the typed fields reject non-finite numbers while parsing; the free metadata is checked here
    non_finite = first_non_finite(doc.get("sensor_setup", {}), "sensor_setup")
    if non_finite is not None:
        raise UploadError(f"{non_finite}: number must be finite", location=non_finite, reason="non_finite")
    bad = np.flatnonzero(np.diff(times_s) <= 0)
    if bad.size:
        i = int(bad[0]) + 1
        raise UploadError(
            f"frame {i}, field t: t={float(times_s[i])!r} is not after the previous frame's t={float(times_s[i - 1])!r}"
            " (t must be strictly increasing)",
            location=f"frames[{i}].t",
            reason="time_order",
        )


def validate_upload_json(body: bytes | bytearray | str) -> dict[str, Any]:
    """Validate a raw JSON upload; return the parsed document.

    Raises :class:`UploadError` naming the frame and field of the first problem.
    """
    try:
        doc = cast(dict[str, Any], _ADAPTER.validate_json(body))
    except ValidationError as exc:
        raise _error_from_pydantic(exc) from None
    _check_version(doc)
    _check_semantics(doc, _frame_times_s(doc))
    return doc


def validate_upload(doc: Any) -> dict[str, Any]:
    """Validate an already parsed document (a dict), as :func:`validate_upload_json`."""
    _check_version(doc)
    try:
        valid = cast(dict[str, Any], _ADAPTER.validate_python(doc))
    except ValidationError as exc:
        raise _error_from_pydantic(exc) from None
    _check_semantics(valid, _frame_times_s(valid))
    return valid


def _decode_element(raw: dict[str, Any]) -> PerceivedElement:
    style = raw.get("style")
    return PerceivedElement(
        type=ElementType(raw["type"]),
        points_xy_vehicle=np.asarray(raw["points"], float),
        style=DividerStyle(style) if style is not None else None,
        score=float(raw.get("score", float("nan"))),
        track_id=raw.get("track_id"),
    )


def decode_trip(doc: dict[str, Any]) -> Trip:
    """A validated upload document -> :class:`Trip` (arrays in upload order)."""
    frames = doc["frames"]
    n = len(frames)
    nan = float("nan")
    return Trip(
        vehicle_id=doc["vehicle_id"],
        trip_id=doc["trip_id"],
        started_at=doc["started_at"],
        timestamps_s=np.fromiter((f["t"] for f in frames), float, n),
        gnss_lonlat_deg=np.array([(f["gnss"]["lon"], f["gnss"]["lat"]) for f in frames], float).reshape(n, 2),
        gnss_status=np.fromiter((GnssStatus.from_name(f["gnss"]["status"]) for f in frames), np.uint8, n),
        gnss_std_m=np.fromiter((f["gnss"].get("std_m", nan) for f in frames), float, n),
        gnss_heading_deg=np.fromiter((f["gnss"].get("heading_deg", nan) for f in frames), float, n),
        odom_xyyaw=np.array(
            [(f["odom"]["x"], f["odom"]["y"], f["odom"]["yaw"]) for f in frames], float
        ).reshape(n, 3),
        elements=tuple(tuple(_decode_element(e) for e in f["elements"]) for f in frames),
        sensor_setup=dict(doc.get("sensor_setup", {})),
    )


def encode_trip(trip: Trip) -> dict[str, Any]:
    """Inverse of :func:`decode_trip` (used by the simulator and tests)."""
    frames = []
    for i in range(trip.n_frames):
        gnss: dict[str, Any] = {
            "lat": float(trip.gnss_lonlat_deg[i, 1]),
            "lon": float(trip.gnss_lonlat_deg[i, 0]),
            "status": GnssStatus(int(trip.gnss_status[i])).wire_name,
        }
        if np.isfinite(trip.gnss_heading_deg[i]):
            gnss["heading_deg"] = float(trip.gnss_heading_deg[i])
        if np.isfinite(trip.gnss_std_m[i]):
            gnss["std_m"] = float(trip.gnss_std_m[i])
        elements = []
        for e in trip.elements[i]:
            out: dict[str, Any] = {"type": e.type.value, "points": e.points_xy_vehicle.tolist()}
            if e.style is not None:
                out["style"] = e.style.value
            if np.isfinite(e.score):
                out["score"] = float(e.score)
            if e.track_id is not None:
                out["track_id"] = int(e.track_id)
            elements.append(out)
        x, y, yaw = trip.odom_xyyaw[i]
        frames.append(
            {
                "t": float(trip.timestamps_s[i]),
                "gnss": gnss,
                "odom": {"x": float(x), "y": float(y), "yaw": float(yaw)},
                "elements": elements,
            }
        )
    doc: dict[str, Any] = {
        "schema_version": SCHEMA_VERSION,
        "vehicle_id": trip.vehicle_id,
        "trip_id": trip.trip_id,
        "started_at": trip.started_at,
    }
    if trip.sensor_setup:
        doc["sensor_setup"] = trip.sensor_setup
    doc["frames"] = frames
    return doc
