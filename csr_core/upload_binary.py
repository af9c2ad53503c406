"""The compact binary trip upload (``application/vnd.csr.trip+cbor``): the same content as the
contract's JSON upload, as one CBOR document (RFC 8949, the ``cbor2`` library) of columns of
quantised, delta-encoded integers. ``docs/upload-binary.md`` is the format's specification.

:func:`encode` takes an upload document (the parsed JSON, a ``dict``) and returns the bytes;
:func:`decode` returns the upload document again, equal to the input within the quantisation
steps (every number is rounded to ``10**-decimals`` of its field: values the JSON already gave
with at most that many decimals come back bit-identical). With ``keyframe_spacing_m`` the
encoder keeps the perceived elements of keyframes only (lossy: other frames decode with
``"elements": []``). :func:`decode` checks the binary structure (raising :class:`UploadError`
naming the column or the frame and field); the decoded document then goes through the same
validation as a JSON upload (``csr_core.upload.validate_upload``).
"""

from __future__ import annotations

import io
import itertools
import math
from collections.abc import Sequence
from dataclasses import asdict, dataclass
from typing import Any

import cbor2
import numpy as np

from csr_core.errors import UploadError
from csr_core.single_trip.keyframes import every_travel_or_time

MEDIA_TYPE = "application/vnd.csr.trip+cbor"
FORMAT = "csr.trip+cbor"
FORMAT_VERSION = 1

GNSS_STATUSES = ("rtk_fixed", "rtk_float", "dgps", "single", "none")
ELEMENT_TYPES = ("lane_divider", "road_boundary", "centerline", "stop_line", "crosswalk", "road_marking")
DIVIDER_STYLES = ("solid", "dashed", "double", "unknown")  # coded 1..4; 0 = no style

# Nesting depth allowed in ``sensor_setup`` (deeper or cyclic CBOR is rejected).
MAX_SENSOR_SETUP_DEPTH = 32
# Largest magnitude of a quantised integer: every code is exact as a float64.
MAX_CODE = 2**53
# Largest magnitude of a step between two track ids (integers, not quantised)
MAX_TRACK_STEP = 2**65


@dataclass(frozen=True, slots=True)
class Decimals:
    """Quantisation steps as decimal digits: a field is stored as ``round(value * 10**d)``.

    The defaults are the precision the fleet's JSON carries (the simulator rounds to these;
    measurement noise is far larger): 1 ms, 1e-9 degrees (0.1 mm), 1 mm, 1 microradian,
    0.001 degree, 1 mm, 1 mm in the vehicle frame, 0.001 of score."""

    t_s: int = 3
    latlon_deg: int = 9
    odom_m: int = 3
    odom_yaw_rad: int = 6
    heading_deg: int = 3
    std_m: int = 3
    point_m: int = 3
    score: int = 3


@dataclass(frozen=True, slots=True)
class EncodeOptions:
    """``keyframe_spacing_m``: keep elements only on frames at least this much odometry travel
    (or ``keyframe_period_s``) after the previous kept frame, and on the last; ``None`` keeps
    every frame's elements (lossless in structure)."""

    decimals: Decimals = Decimals()
    keyframe_spacing_m: float | None = None
    keyframe_period_s: float = 1.0


# --- encoding -------------------------------------------------------------------------------------


def _codes(values: Sequence[float] | np.ndarray, decimals: int, what: str) -> np.ndarray:
    scaled = np.asarray(values, dtype=np.float64) * 10.0**decimals
    if scaled.size and not np.all(np.abs(scaled) < MAX_CODE):
        raise ValueError(
            f"{what}: a value is too large for 10**-{decimals} steps (|value| * 10**{decimals} >= 2**53)"
        )
    return np.rint(scaled).astype(np.int64)


def _delta(codes: np.ndarray) -> list[int]:
    return np.diff(codes, prepend=np.int64(0)).tolist()


def _optional_delta(values: list[float | None], decimals: int, what: str) -> list[int | None]:
    present = [v for v in values if v is not None]
    deltas = iter(_delta(_codes(present, decimals, what)))
    return [None if v is None else next(deltas) for v in values]


def keyframes_by_odometry(frames: list[dict[str, Any]], spacing_m: float, period_s: float) -> np.ndarray:
    """Frame indices (K,) whose perception a keyframe-only encoding keeps: the first and last
    frame and each frame ``spacing_m`` of odometry travel or ``period_s`` after the previous one
    (the selection of ``csr_core.single_trip.keyframes``)."""
    xy = np.array([(f["odom"]["x"], f["odom"]["y"]) for f in frames], float).reshape(-1, 2)
    travel_m = np.r_[0.0, np.cumsum(np.linalg.norm(np.diff(xy, axis=0), axis=1))]
    t_s = np.array([f["t"] for f in frames], float)
    return every_travel_or_time(travel_m, t_s, spacing_m, period_s, keep_last=True)


def encode(doc: dict[str, Any], options: EncodeOptions = EncodeOptions()) -> bytes:
    """A (valid) upload document -> the CBOR bytes. Raises ``ValueError`` for a number too large
    to quantise exactly (``|value| * 10**decimals >= 2**53``)."""
    d = options.decimals
    frames = doc["frames"]
    gnss = [f["gnss"] for f in frames]
    kept = range(len(frames))
    if options.keyframe_spacing_m is not None:
        kept = keyframes_by_odometry(frames, options.keyframe_spacing_m, options.keyframe_period_s).tolist()
    kept_set = set(kept)
    elements = [e for i, f in enumerate(frames) if i in kept_set for e in f["elements"]]
    points = [np.asarray(e["points"], dtype=np.float64).reshape(-1, 2) for e in elements]
    n_points = [len(p) for p in points]
    xy = _codes(np.concatenate(points) if points else np.zeros((0, 2)), d.point_m, "elements.points")
    xy_delta = np.diff(xy, axis=0, prepend=np.zeros((1, 2), np.int64)) if len(xy) else xy
    starts = np.cumsum([0, *n_points[:-1]])[: len(n_points)]
    xy_delta[starts] = xy[starts]  # each element's first point absolute, the rest as steps
    frame_columns: dict[str, Any] = {
        "t": _delta(_codes([f["t"] for f in frames], d.t_s, "frames.t")),
        "lat": _delta(_codes([g["lat"] for g in gnss], d.latlon_deg, "frames.gnss.lat")),
        "lon": _delta(_codes([g["lon"] for g in gnss], d.latlon_deg, "frames.gnss.lon")),
        "status": [GNSS_STATUSES.index(g["status"]) for g in gnss],
        "heading": _optional_delta(
            [g.get("heading_deg") for g in gnss], d.heading_deg, "frames.gnss.heading_deg"
        ),
        "std": _optional_delta([g.get("std_m") for g in gnss], d.std_m, "frames.gnss.std_m"),
        "x": _delta(_codes([f["odom"]["x"] for f in frames], d.odom_m, "frames.odom.x")),
        "y": _delta(_codes([f["odom"]["y"] for f in frames], d.odom_m, "frames.odom.y")),
        "yaw": _delta(_codes([f["odom"]["yaw"] for f in frames], d.odom_yaw_rad, "frames.odom.yaw")),
        "n_elements": [len(frames[i]["elements"]) if i in kept_set else 0 for i in range(len(frames))],
    }
    scores = [e.get("score") for e in elements]
    score_codes = iter(_codes([s for s in scores if s is not None], d.score, "elements.score").tolist())
    tracks = [e.get("track_id") for e in elements]
    previous_track = 0
    track_deltas: list[int | None] = []
    for track in tracks:
        if track is None:
            track_deltas.append(None)
        else:
            track_deltas.append(int(track) - previous_track)
            previous_track = int(track)
    element_columns = {
        "type": [ELEMENT_TYPES.index(e["type"]) for e in elements],
        "style": [DIVIDER_STYLES.index(e["style"]) + 1 if "style" in e else 0 for e in elements],
        "score": [None if s is None else next(score_codes) for s in scores],
        "track": track_deltas,
        "n_points": n_points,
        "x": xy_delta[:, 0].tolist(),
        "y": xy_delta[:, 1].tolist(),
    }
    out: dict[str, Any] = {
        "format": FORMAT,
        "format_version": FORMAT_VERSION,
        "decimals": asdict(d),
        "keyframe_only": options.keyframe_spacing_m is not None,
        "schema_version": doc["schema_version"],
        "vehicle_id": doc["vehicle_id"],
        "trip_id": doc["trip_id"],
        "started_at": doc["started_at"],
    }
    if "sensor_setup" in doc:
        out["sensor_setup"] = doc["sensor_setup"]
    out["frames"] = frame_columns
    out["elements"] = element_columns
    return bytes(cbor2.dumps(out))


# --- decoding -------------------------------------------------------------------------------------


def _bad(message: str, location: str) -> UploadError:
    return UploadError(f"{location}: {message}", location=location, reason="binary")


def _is_int(value: Any) -> bool:
    return type(value) is int


def _int_column(
    table: dict[str, Any],
    table_name: str,
    name: str,
    length: int,
    *,
    nullable: bool = False,
    limit: int = MAX_CODE,
) -> list:
    where = f"{table_name}.{name}"
    if name not in table:
        raise _bad("missing column", where)
    column = table[name]
    if not isinstance(column, list):
        raise _bad(f"must be an array, not {type(column).__name__}", where)
    if len(column) != length:
        raise _bad(f"has {len(column)} entries, expected {length}", where)
    for i, value in enumerate(column):
        if not (_is_int(value) and abs(value) < limit) and not (nullable and value is None):
            kind = "an integer or null" if nullable else "an integer"
            bound = f"2**{limit.bit_length() - 1}"
            raise _bad(f"entry {i} must be {kind} of magnitude below {bound}, not {value!r}", f"{where}[{i}]")
    return column


def _undelta(deltas: list[int], decimals: int, where: str) -> list[float]:
    codes = list(itertools.accumulate(deltas))
    for i, code in enumerate(codes):
        if abs(code) >= MAX_CODE:
            raise _bad("the running sum of the steps leaves the range of exact values", f"{where}[{i}]")
    return (np.asarray(codes, dtype=np.float64) / 10.0**decimals).tolist()


def _optional_undelta(deltas: list[int | None], decimals: int, where: str) -> list[float | None]:
    values = iter(_undelta([v for v in deltas if v is not None], decimals, where))
    return [None if v is None else next(values) for v in deltas]


def _json_value(value: Any, location: str, depth: int = 0) -> None:
    """Reject what JSON cannot hold (byte strings, tags, non-string keys) and deep or cyclic
    nesting in the free ``sensor_setup``."""
    if depth > MAX_SENSOR_SETUP_DEPTH:
        raise _bad(f"nested deeper than {MAX_SENSOR_SETUP_DEPTH} levels", location)
    if value is None or isinstance(value, bool | int | float | str):
        return
    if isinstance(value, list):
        for i, item in enumerate(value):
            _json_value(item, f"{location}[{i}]", depth + 1)
        return
    if isinstance(value, dict):
        for key, item in value.items():
            if not isinstance(key, str):
                raise _bad(f"map keys must be text, not {type(key).__name__}", location)
            _json_value(item, f"{location}.{key}", depth + 1)
        return
    raise _bad(f"{type(value).__name__} has no JSON equivalent", location)


def _enum(codes: list[int], names: Sequence[str], where: str, *, offset: int = 0) -> list[str | None]:
    out: list[str | None] = []
    for i, code in enumerate(codes):
        if code == 0 and offset:
            out.append(None)
        elif 0 <= code - offset < len(names):
            out.append(names[code - offset])
        else:
            raise _bad(f"unknown code {code} (0..{len(names) - 1 + offset})", where.format(i=i))
    return out


def _decimals(raw: Any) -> Decimals:
    if not isinstance(raw, dict):
        raise _bad("must be a map of decimal digits", "decimals")
    values: dict[str, int] = {}
    for name in Decimals.__dataclass_fields__:
        value = raw.get(name)
        if not (isinstance(value, int) and _is_int(value) and 0 <= value <= 12):
            raise _bad(f"must be an integer 0..12, not {value!r}", f"decimals.{name}")
        values[name] = value
    return Decimals(**values)


_HEADER_KEYS = frozenset(
    ("format", "format_version", "decimals", "keyframe_only", "schema_version", "vehicle_id", "trip_id")
    + ("started_at", "sensor_setup", "frames", "elements")
)
_FRAME_COLUMNS = frozenset(("t", "lat", "lon", "status", "heading", "std", "x", "y", "yaw", "n_elements"))
_ELEMENT_COLUMNS = frozenset(("type", "style", "score", "track", "n_points", "x", "y"))


def _header(doc: Any) -> tuple[Decimals, dict[str, Any], dict[str, Any]]:
    if not isinstance(doc, dict):
        raise _bad(f"the document must be a CBOR map, not {type(doc).__name__}", "")
    if doc.get("format") != FORMAT:
        raise _bad(f"must be {FORMAT!r}, not {doc.get('format')!r}", "format")
    if doc.get("format_version") != FORMAT_VERSION:
        raise _bad(
            f"this server reads version {FORMAT_VERSION}, not {doc.get('format_version')!r}", "format_version"
        )
    unknown = [key for key in doc if key not in _HEADER_KEYS]
    if unknown:
        raise _bad(f"unknown key {unknown[0]!r}", str(unknown[0]))
    tables = []
    for name, columns in (("frames", _FRAME_COLUMNS), ("elements", _ELEMENT_COLUMNS)):
        if not isinstance(doc.get(name), dict):
            raise _bad("must be a map of columns", name)
        unknown = [key for key in doc[name] if key not in columns]
        if unknown:
            raise _bad(f"unknown column {unknown[0]!r}", f"{name}.{unknown[0]}")
        tables.append(doc[name])
    return _decimals(doc.get("decimals")), tables[0], tables[1]


def _frame_dicts(frames: dict[str, Any], d: Decimals) -> tuple[list[dict[str, Any]], list[int]]:
    if "t" not in frames:
        raise _bad("missing column", "frames.t")
    if not isinstance(frames["t"], list):
        raise _bad(f"must be an array, not {type(frames['t']).__name__}", "frames.t")
    n = len(frames["t"])
    column = {
        name: _int_column(frames, "frames", name, n)
        for name in ("t", "lat", "lon", "status", "x", "y", "yaw")
    }
    optional = {name: _int_column(frames, "frames", name, n, nullable=True) for name in ("heading", "std")}
    n_elements = _int_column(frames, "frames", "n_elements", n)
    for i, count in enumerate(n_elements):
        if count < 0:
            raise _bad(f"must not be negative, not {count}", f"frames.n_elements[{i}]")
    t = _undelta(column["t"], d.t_s, "frames.t")
    lat = _undelta(column["lat"], d.latlon_deg, "frames.lat")
    lon = _undelta(column["lon"], d.latlon_deg, "frames.lon")
    status = _enum(column["status"], GNSS_STATUSES, "frames[{i}].gnss.status")
    heading = _optional_undelta(optional["heading"], d.heading_deg, "frames.heading")
    std = _optional_undelta(optional["std"], d.std_m, "frames.std")
    x = _undelta(column["x"], d.odom_m, "frames.x")
    y = _undelta(column["y"], d.odom_m, "frames.y")
    yaw = _undelta(column["yaw"], d.odom_yaw_rad, "frames.yaw")
    out = []
    for i in range(n):
        gnss: dict[str, Any] = {"lat": lat[i], "lon": lon[i], "status": status[i]}
        if heading[i] is not None:
            gnss["heading_deg"] = heading[i]
        if std[i] is not None:
            gnss["std_m"] = std[i]
        out.append({"t": t[i], "gnss": gnss, "odom": {"x": x[i], "y": y[i], "yaw": yaw[i]}, "elements": []})
    return out, n_elements


def _element_dicts(elements: dict[str, Any], d: Decimals, n_total: int) -> list[dict[str, Any]]:
    types = _enum(_int_column(elements, "elements", "type", n_total), ELEMENT_TYPES, "elements.type[{i}]")
    styles = _enum(
        _int_column(elements, "elements", "style", n_total), DIVIDER_STYLES, "elements.style[{i}]", offset=1
    )
    score_codes = _int_column(elements, "elements", "score", n_total, nullable=True)
    scores = [None if s is None else s / 10.0**d.score for s in score_codes]
    track_deltas = _int_column(elements, "elements", "track", n_total, nullable=True, limit=MAX_TRACK_STEP)
    n_points = _int_column(elements, "elements", "n_points", n_total)
    for i, count in enumerate(n_points):
        if count < 0:
            raise _bad(f"must not be negative, not {count}", f"elements.n_points[{i}]")
    total_points = sum(n_points)
    x_steps = _int_column(elements, "elements", "x", total_points)
    y_steps = _int_column(elements, "elements", "y", total_points)
    # the first point of each element is absolute: the running sum restarts there
    x_codes: list[int] = []
    y_codes: list[int] = []
    start = 0
    for count in n_points:
        x_codes += itertools.accumulate(x_steps[start : start + count])
        y_codes += itertools.accumulate(y_steps[start : start + count])
        start += count
    for name, codes in (("x", x_codes), ("y", y_codes)):
        if codes and max(map(abs, codes)) >= MAX_CODE:
            raise _bad("a running sum of the steps leaves the range of exact values", f"elements.{name}")
    points = (np.column_stack([x_codes, y_codes]).astype(np.float64) / 10.0**d.point_m).tolist()
    out = []
    start, track = 0, 0
    for i in range(n_total):
        element: dict[str, Any] = {"type": types[i], "points": points[start : start + n_points[i]]}
        if styles[i] is not None:
            element["style"] = styles[i]
        if scores[i] is not None:
            element["score"] = scores[i]
        step = track_deltas[i]
        if step is not None:
            track += step
            element["track_id"] = track
        out.append(element)
        start += n_points[i]
    return out


def decode(data: bytes | bytearray) -> dict[str, Any]:
    """The CBOR bytes -> the upload document (not yet validated against the schema).

    Raises :class:`UploadError`: reason ``cbor`` for bytes that are not one well-formed CBOR
    item, ``binary`` for a CBOR document that is not this format (``location`` names the column
    or entry, e.g. ``elements.n_points[3]``)."""
    stream = io.BytesIO(data)
    try:
        doc = cbor2.CBORDecoder(stream).decode()
    except (cbor2.CBORDecodeError, RecursionError, ValueError, OverflowError, MemoryError) as exc:
        raise UploadError(f"malformed CBOR: {exc}", location="", reason="cbor") from None
    if stream.tell() != len(data):
        raise UploadError(
            f"malformed CBOR: {len(data) - stream.tell()} bytes after the document",
            location="",
            reason="cbor",
        )
    d, frames, elements = _header(doc)
    frame_dicts, n_elements = _frame_dicts(frames, d)
    element_dicts = _element_dicts(elements, d, sum(n_elements))
    start = 0
    for frame, count in zip(frame_dicts, n_elements, strict=True):
        frame["elements"] = element_dicts[start : start + count]
        start += count
    out: dict[str, Any] = {}
    for name in ("schema_version", "vehicle_id", "trip_id", "started_at", "sensor_setup"):
        if name in doc:
            out[name] = doc[name]
    if "sensor_setup" in out:
        _json_value(out["sensor_setup"], "sensor_setup")
    out["frames"] = frame_dicts
    return out


def quantisation_bound(decimals: int, magnitude: float = 1.0) -> float:
    """The largest difference between a value of at most ``magnitude`` and its decoded copy:
    half a step, plus the float64 rounding of scaling and dividing (two units in the last place)."""
    return 0.5 * 10.0**-decimals + 2 * math.ulp(magnitude)
