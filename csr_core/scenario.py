"""Scenario folders (contract section 5) and reconstruction outputs (contract section 4).

Reading::

    scenario.json                          {"name", "origin": {"lat", "lon"}, "profile": {...}}
    trips/<vehicle_id>__<trip_id>.json.gz  one trip upload each (contract section 1)
    truth/poses/<key>.csv                  t,lat,lon,heading_deg; one row per uploaded frame
    truth/map.geojson                      features as in GET /v1/map

Writing (``csr reconstruct SCENARIO_DIR --out OUT_DIR``)::

    OUT_DIR/poses/<key>.csv    t,lat,lon,heading_deg; one row per uploaded frame, upload order
    OUT_DIR/map.geojson        FeatureCollection: LineString for line types, Polygon for
                               crosswalk / road_marking; properties.type (+ style, id)
    OUT_DIR/report.json        per-trip status, failure reasons, timings (not in the contract)

A trip that failed gets no CSV; it is listed in ``report.json`` under ``failed`` with its reason.
Everything here is file I/O around the core types; the reconstruction never reads ``truth/``.
"""

from __future__ import annotations

import gzip
import json
import logging
from collections.abc import Iterable, Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import orjson

from csr_core.errors import ScenarioError, UploadError
from csr_core.geo import LocalFrame
from csr_core.types import DividerStyle, ElementType, MapFeature, Reconstruction, Trip
from csr_core.upload import decode_trip, validate_upload_json

log = logging.getLogger(__name__)

POSES_CSV_HEADER = "t,lat,lon,heading_deg"
TRIP_SUFFIX = ".json.gz"


# --- reading -----------------------------------------------------------------------------------


@dataclass(frozen=True, slots=True)
class TripFile:
    """One uploaded trip file: ``key`` is ``<vehicle_id>__<trip_id>``; ``n_bytes`` the body as sent."""

    key: str
    path: Path
    n_bytes: int


@dataclass(frozen=True, slots=True)
class ScenarioMeta:
    name: str
    origin_lat: float
    origin_lon: float
    profile: dict = field(default_factory=dict)

    @property
    def frame(self) -> LocalFrame:
        """The evaluation plane (contract section 6): tmerc centred on the scenario origin."""
        return LocalFrame(origin_lat=self.origin_lat, origin_lon=self.origin_lon)


@dataclass(frozen=True, slots=True)
class PoseTrack:
    """Poses as in a poses CSV: ``timestamps_s (N,)``, ``lonlat_deg (N, 2)``, ``heading_deg (N,)``."""

    timestamps_s: np.ndarray
    lonlat_deg: np.ndarray
    heading_deg: np.ndarray


@dataclass(frozen=True, slots=True)
class GeoFeature:
    """One map feature in geographic coordinates; ``lonlat_deg (M, 2)``, polygons without the
    repeated closing point."""

    type: ElementType
    lonlat_deg: np.ndarray
    style: DividerStyle | None = None
    feature_id: str = ""


def _require_dir(path: Path, what: str) -> Path:
    if not path.is_dir():
        raise ScenarioError(f"{what} not found: {path}")
    return path


def list_trip_files(scenario_dir: str | Path) -> list[TripFile]:
    """The trips of a scenario in file-name order (the order they count as uploaded)."""
    scenario_dir = _require_dir(Path(scenario_dir), "scenario folder")
    trips_dir = _require_dir(scenario_dir / "trips", "trips folder")
    paths = sorted(p for p in trips_dir.iterdir() if p.name.endswith(TRIP_SUFFIX))
    if not paths:
        raise ScenarioError(f"no trips ({'*' + TRIP_SUFFIX}) in {trips_dir}")
    return [TripFile(key=p.name[: -len(TRIP_SUFFIX)], path=p, n_bytes=p.stat().st_size) for p in paths]


def load_trip(trip_file: TripFile) -> Trip:
    """Gunzip, validate (contract section 1) and decode one trip; errors name the file."""
    try:
        body = gzip.decompress(trip_file.path.read_bytes())
    except (OSError, EOFError) as exc:
        raise ScenarioError(f"{trip_file.path}: not a readable gzip file ({exc})") from exc
    try:
        trip = decode_trip(validate_upload_json(body))
    except UploadError as exc:
        raise ScenarioError(f"{trip_file.path}: invalid trip upload: {exc.message}") from exc
    if trip.key != trip_file.key:
        raise ScenarioError(
            f"{trip_file.path}: file name says {trip_file.key!r} but the upload is {trip.key!r}"
        )
    return trip


def read_scenario_meta(scenario_dir: str | Path) -> ScenarioMeta:
    path = Path(scenario_dir) / "scenario.json"
    try:
        doc = json.loads(path.read_text())
        return ScenarioMeta(
            name=str(doc.get("name", Path(scenario_dir).name)),
            origin_lat=float(doc["origin"]["lat"]),
            origin_lon=float(doc["origin"]["lon"]),
            profile=dict(doc.get("profile", {})),
        )
    except FileNotFoundError as exc:
        raise ScenarioError(f"{path}: missing") from exc
    except (ValueError, KeyError, TypeError) as exc:
        raise ScenarioError(f"{path}: malformed ({exc!r})") from exc


def read_poses_csv(path: str | Path) -> PoseTrack:
    """A ``t,lat,lon,heading_deg`` CSV (truth or output) -> :class:`PoseTrack`."""
    path = Path(path)
    try:
        with path.open() as fh:
            header = fh.readline().strip()
            if header != POSES_CSV_HEADER:
                raise ScenarioError(f"{path}: header must be {POSES_CSV_HEADER!r}, got {header!r}")
            rows = np.loadtxt(fh, delimiter=",", ndmin=2, dtype=float)
    except FileNotFoundError as exc:
        raise ScenarioError(f"{path}: missing") from exc
    except ValueError as exc:
        raise ScenarioError(f"{path}: malformed ({exc})") from exc
    if rows.size == 0:
        rows = np.zeros((0, 4))
    if rows.shape[1] != 4:
        raise ScenarioError(f"{path}: expected 4 columns, got {rows.shape[1]}")
    return PoseTrack(timestamps_s=rows[:, 0], lonlat_deg=rows[:, [2, 1]], heading_deg=rows[:, 3])


def read_poses_dir(poses_dir: str | Path) -> dict[str, PoseTrack]:
    poses_dir = Path(poses_dir)
    if not poses_dir.is_dir():
        raise ScenarioError(f"poses folder not found: {poses_dir}")
    return {p.stem: read_poses_csv(p) for p in sorted(poses_dir.glob("*.csv"))}


def _geometry_parts(geometry: dict) -> Iterable[tuple[list, bool]]:
    kind, coords = geometry.get("type"), geometry.get("coordinates")
    if not isinstance(coords, list):
        raise ValueError("geometry without coordinates")
    if kind == "LineString":
        yield coords, False
    elif kind == "MultiLineString":
        for line in coords:
            yield line, False
    elif kind == "Polygon":
        yield coords[0], True
    elif kind == "MultiPolygon":
        for poly in coords:
            yield poly[0], True
    else:
        raise ValueError(f"unsupported geometry type {kind!r}")


def read_map_geojson(path: str | Path) -> list[GeoFeature]:
    """A FeatureCollection as written by ``GET /v1/map`` -> features (multi-geometries split).
    Unknown ``properties.type`` values are skipped with a warning."""
    path = Path(path)
    try:
        doc = orjson.loads(path.read_bytes())
    except FileNotFoundError as exc:
        raise ScenarioError(f"{path}: missing") from exc
    except orjson.JSONDecodeError as exc:
        raise ScenarioError(f"{path}: malformed JSON ({exc})") from exc
    out: list[GeoFeature] = []
    for i, feat in enumerate(doc.get("features", [])):
        props = feat.get("properties") or {}
        try:
            etype = ElementType(props.get("type"))
        except ValueError:
            log.warning("%s: feature %d has unknown type %r; skipped", path, i, props.get("type"))
            continue
        style = props.get("style")
        try:
            parts = list(_geometry_parts(feat.get("geometry") or {}))
        except (ValueError, TypeError, IndexError) as exc:
            raise ScenarioError(f"{path}: feature {i}: {exc}") from exc
        for coords, closed in parts:
            lonlat = np.asarray(coords, float).reshape(-1, 2)
            if closed and len(lonlat) > 1 and np.array_equal(lonlat[0], lonlat[-1]):
                lonlat = lonlat[:-1]
            out.append(
                GeoFeature(
                    type=etype,
                    lonlat_deg=lonlat,
                    style=DividerStyle(style) if style in DividerStyle._value2member_map_ else None,
                    feature_id=str(feat.get("id", props.get("id", ""))),
                )
            )
    return out


def geo_features_to_local(features: Sequence[GeoFeature], frame: LocalFrame) -> tuple[MapFeature, ...]:
    """Project map features into a local plane (one pyproj call for all vertices)."""
    if not features:
        return ()
    all_xy = frame.to_local(np.concatenate([f.lonlat_deg for f in features]))
    ends = np.cumsum([len(f.lonlat_deg) for f in features])
    parts = np.split(all_xy, ends[:-1])
    return tuple(
        MapFeature(type=f.type, points_xy_world=xy, style=f.style, feature_id=f.feature_id)
        for f, xy in zip(features, parts, strict=False)
    )


# --- writing -----------------------------------------------------------------------------------


def _poses_csv_bytes(timestamps_s: np.ndarray, lonlat_deg: np.ndarray, heading_deg: np.ndarray) -> bytes:
    rows = np.column_stack([timestamps_s, lonlat_deg[:, 1], lonlat_deg[:, 0], heading_deg])
    lines = [POSES_CSV_HEADER]
    lines += [f"{t:.3f},{lat:.9f},{lon:.9f},{h:.4f}" for t, lat, lon, h in rows.tolist()]
    return ("\n".join(lines) + "\n").encode()


def map_features_to_geojson(
    features: Sequence[MapFeature], frame: LocalFrame, extra: dict | None = None
) -> dict:
    """Map features (world plane of ``frame``) -> GeoJSON FeatureCollection like ``GET /v1/map``;
    ``extra`` is added to every feature's properties."""
    out: list[dict] = []
    if not features:
        return {"type": "FeatureCollection", "features": out}
    lonlat_all = frame.to_lonlat(np.concatenate([f.points_xy_world for f in features]))
    start = 0
    for i, f in enumerate(features):
        n = len(f.points_xy_world)
        lonlat = np.round(lonlat_all[start : start + n], 9).tolist()
        start += n
        if f.type.is_polygon:
            geometry = {"type": "Polygon", "coordinates": [lonlat + [lonlat[0]]]}
        else:
            geometry = {"type": "LineString", "coordinates": lonlat}
        fid = f.feature_id or f"f{i}"
        props: dict = {"type": f.type.value, "id": fid}
        if f.style is not None:
            props["style"] = f.style.value
        props.update({k: v for k, v in f.properties.items() if k not in props})
        props.update(extra or {})
        out.append({"type": "Feature", "id": fid, "geometry": geometry, "properties": props})
    return {"type": "FeatureCollection", "features": out}


def write_reconstruction(
    recon: Reconstruction, trips: Sequence[Trip], out_dir: str | Path, report: dict | None = None
) -> Path:
    """Write ``OUT_DIR/poses/*.csv``, ``OUT_DIR/map.geojson``, ``OUT_DIR/held_back.geojson`` (lines
    kept out of the map, each with ``"status": "held_back"``, like ``GET /v1/tiles/{z}/{x}/{y}/held-back``)
    and ``OUT_DIR/report.json``.

    Each CSV has one row per uploaded frame of its trip, in upload order, with the trip's own
    ``t``; trips in ``recon.failed`` (or without poses) get no CSV and are listed in the report.
    CSVs already in ``OUT_DIR/poses`` are removed first.
    """
    out_dir = Path(out_dir)
    poses_dir = out_dir / "poses"
    poses_dir.mkdir(parents=True, exist_ok=True)
    for stale in poses_dir.glob("*.csv"):  # a re-run must not leave CSVs of trips that now failed
        stale.unlink()
    frame = LocalFrame(origin_lat=recon.origin_lat, origin_lon=recon.origin_lon)
    failed = dict(recon.failed)
    written = []
    for trip in trips:
        poses = recon.poses_xyyaw_world.get(trip.key)
        if poses is None:
            failed.setdefault(trip.key, "no poses")
            continue
        if poses.shape != (trip.n_frames, 3):
            raise ValueError(f"{trip.key}: poses shape {poses.shape} != ({trip.n_frames}, 3)")
        lonlat = frame.to_lonlat(poses[:, :2])
        body = _poses_csv_bytes(trip.timestamps_s, lonlat, frame.heading_deg(poses[:, 2], lonlat))
        (poses_dir / f"{trip.key}.csv").write_bytes(body)
        written.append(trip.key)
    geojson = map_features_to_geojson(recon.map_features, frame)
    (out_dir / "map.geojson").write_bytes(orjson.dumps(geojson))
    held_back = map_features_to_geojson(recon.held_back_features, frame, extra={"status": "held_back"})
    (out_dir / "held_back.geojson").write_bytes(orjson.dumps(held_back))
    full_report = {
        "origin": {"lat": recon.origin_lat, "lon": recon.origin_lon},
        "trips": len(trips),
        "trips_with_poses": len(written),
        "failed": failed,
        "degraded": dict(recon.degraded),
        "map_features": len(recon.map_features),
        "diagnostics": recon.diagnostics,
    }
    full_report.update(report or {})
    (out_dir / "report.json").write_bytes(
        orjson.dumps(full_report, option=orjson.OPT_INDENT_2 | orjson.OPT_SERIALIZE_NUMPY)
    )
    return out_dir
