"""Exports of the road structure to other HD-map formats (pure: no service layers).

```python
from csr_core.export import export_lanelet2_geojson
xml_bytes, report = export_lanelet2_geojson(feature_collection)   # GeoJSON like GET /v1/map
```
"""

from __future__ import annotations

from collections.abc import Iterable

from csr_core.export.inputs import LonLatFeature, lonlat_features_from_geojson, to_local
from csr_core.export.lanelet2 import (
    DEFAULT,
    ExportError,
    ExportReport,
    Lanelet2Map,
    Lanelet2Params,
    build_lanelet2_map,
)
from csr_core.export.osm import ValidationResult, to_osm_xml, validate_lanelet2_osm
from csr_core.geo import LocalFrame

__all__ = [
    "DEFAULT",
    "ExportError",
    "ExportReport",
    "Lanelet2Map",
    "Lanelet2Params",
    "LonLatFeature",
    "ValidationResult",
    "build_lanelet2_map",
    "export_lanelet2",
    "export_lanelet2_geojson",
    "lonlat_features_from_geojson",
    "to_local",
    "to_osm_xml",
    "validate_lanelet2_osm",
]


def export_lanelet2(
    features: Iterable[LonLatFeature], params: Lanelet2Params = DEFAULT, frame: LocalFrame | None = None
) -> tuple[bytes, Lanelet2Map]:
    """Lon/lat features -> (Lanelet2 OSM XML, the map with its report). ``frame``: the plane of
    the work and of the nodes' ``local_x``/``local_y`` (default: around the features)."""
    frame, local = to_local(list(features), frame)
    m = build_lanelet2_map(local, frame, params)
    return to_osm_xml(m), m


def export_lanelet2_geojson(
    doc: dict, params: Lanelet2Params = DEFAULT
) -> tuple[bytes, Lanelet2Map, dict[str, int]]:
    """A GeoJSON FeatureCollection -> (XML, map, counts of input features ignored by reason)."""
    features, ignored = lonlat_features_from_geojson(doc)
    xml_bytes, m = export_lanelet2(features, params)
    return xml_bytes, m, ignored
