"""Input adapters of the export: map features in lon/lat (a GeoJSON FeatureCollection as
``GET /v1/map`` and ``csr reconstruct``'s ``map.geojson`` give, or (type, style, id, lon/lat)
records from the service) -> ``MapFeature`` in a local plane around them."""

from __future__ import annotations

from collections.abc import Iterable, Sequence
from dataclasses import dataclass, field

import numpy as np

from csr_core.export.lanelet2 import ExportError
from csr_core.geo import LocalFrame
from csr_core.types import DividerStyle, ElementType, MapFeature


@dataclass(frozen=True, slots=True)
class LonLatFeature:
    """One map feature in lon/lat degrees; polygons: outline, first point not repeated."""

    type: ElementType
    lonlat_deg: np.ndarray  # (M, 2)
    style: DividerStyle | None = None
    feature_id: str = ""
    properties: dict = field(default_factory=dict)

    def __post_init__(self) -> None:
        if self.lonlat_deg.ndim != 2 or self.lonlat_deg.shape[1] != 2:
            raise ValueError(f"lonlat_deg must have shape (M, 2), got {self.lonlat_deg.shape}")


def _parts(geometry: dict) -> list[tuple[list, bool]]:
    kind, coords = geometry.get("type"), geometry.get("coordinates")
    if not isinstance(coords, list):
        raise ValueError("geometry without coordinates")
    if kind == "LineString":
        return [(coords, False)]
    if kind == "MultiLineString":
        return [(c, False) for c in coords]
    if kind == "Polygon":
        return [(coords[0], True)]
    if kind == "MultiPolygon":
        return [(c[0], True) for c in coords]
    raise ValueError(f"unsupported geometry type {kind!r}")


def lonlat_features_from_geojson(doc: dict) -> tuple[list[LonLatFeature], dict[str, int]]:
    """Features of a FeatureCollection (multi-geometries split) and counts of what was ignored
    (``unknown type``, ``no geometry``). A malformed geometry raises ``ExportError`` naming it."""
    if not isinstance(doc, dict) or doc.get("type") != "FeatureCollection":
        raise ExportError("input is not a GeoJSON FeatureCollection")
    out: list[LonLatFeature] = []
    ignored: dict[str, int] = {}
    for i, feat in enumerate(doc.get("features") or []):
        props = (feat or {}).get("properties") or {}
        try:
            etype = ElementType(props.get("type"))
        except ValueError:
            ignored["unknown type"] = ignored.get("unknown type", 0) + 1
            continue
        if not feat.get("geometry"):
            ignored["no geometry"] = ignored.get("no geometry", 0) + 1
            continue
        try:
            parts = _parts(feat["geometry"])
            arrays = [np.asarray(c, float).reshape(-1, np.asarray(c).shape[-1])[:, :2] for c, _ in parts]
        except (ValueError, TypeError, IndexError) as exc:
            raise ExportError(f"features[{i}].geometry: {exc}") from exc
        style = props.get("style")
        fid = str(feat.get("id", props.get("id", "")) or "")
        for (_, closed), lonlat in zip(parts, arrays, strict=True):
            if closed and len(lonlat) > 1 and np.array_equal(lonlat[0], lonlat[-1]):
                lonlat = lonlat[:-1]
            if not np.isfinite(lonlat).all():
                raise ExportError(f"features[{i}].geometry: non-finite coordinates")
            out.append(
                LonLatFeature(
                    type=etype,
                    lonlat_deg=lonlat,
                    feature_id=fid,
                    style=DividerStyle(style) if style in DividerStyle._value2member_map_ else None,
                    properties={k: v for k, v in props.items() if k not in ("type", "style", "id")},
                )
            )
    return out, ignored


def to_local(
    features: Sequence[LonLatFeature] | Iterable[LonLatFeature], frame: LocalFrame | None = None
) -> tuple[LocalFrame, tuple[MapFeature, ...]]:
    """Project features into ``frame`` (default: the local plane around them; then at least
    one feature is needed)."""
    features = [f for f in features if len(f.lonlat_deg)]
    if not features:
        if frame is None:
            raise ExportError("no map features to export")
        return frame, ()
    all_lonlat = np.concatenate([f.lonlat_deg for f in features])
    frame = frame or LocalFrame.around(all_lonlat)
    xy = np.split(frame.to_local(all_lonlat), np.cumsum([len(f.lonlat_deg) for f in features])[:-1])
    return frame, tuple(
        MapFeature(
            type=f.type, points_xy_world=p, style=f.style, feature_id=f.feature_id, properties=f.properties
        )
        for f, p in zip(features, xy, strict=True)
    )
