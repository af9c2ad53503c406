"""Calibration of the absolute uncertainty (``csr bench-uncertainty``): does ``sigma_abs_m``
(``topology.absolute_uncertainty``, Eq. 1) describe the raw errors of the map?

Per element of a reconstructed map with a ``sigma_abs_m``: its raw lateral error is the median
distance of its samples (every ``SAMPLE_STEP_M``) to the nearest truth element of its type, in the
scenario's frame with no alignment of map to truth. An element farther than ``UNMATCHED_M`` from
every truth element of its type is a false element, not an error of position (counted apart).
The figures per world: the share of elements whose raw error is within ``2 sigma_abs_m`` (a
Gaussian lateral error: 95.4 %), the same with ``2 uncertainty_m`` (the relative sigma), and the
map's certificate (``tile_certificate`` over all its elements: length-weighted RMS of
``sigma_abs_m``) against the measured length-weighted RMS raw error.
"""

from __future__ import annotations

import json
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from csr_core import metrics
from csr_core.scenario import geo_features_to_local, read_map_geojson, read_scenario_meta
from csr_core.topology.absolute_uncertainty import SIGMA_ABS_PROPERTY, tile_certificate
from csr_core.types import ElementType, MapFeature

SAMPLE_STEP_M = 1.0  # samples along an element
UNMATCHED_M = 3.0  # farther than this from every truth element of its type: a false element
COVERAGE_SIGMAS = 2.0  # the interval whose coverage is measured


@dataclass(frozen=True, slots=True)
class ElementError:
    """One element's raw lateral error (metres), its sigmas and length."""

    error_m: float
    sigma_abs_m: float
    uncertainty_m: float
    length_m: float
    passes: int


@dataclass(frozen=True, slots=True)
class CalibrationRow:
    """One world's calibration: ``coverage_abs`` / ``coverage_rel`` the share of matched elements
    within 2 sigma_abs / 2 uncertainty_m; ``expected_m`` the certificate's absolute error,
    ``measured_m`` the length-weighted RMS raw error."""

    scenario: str
    elements: int
    unmatched: int
    coverage_abs: float
    coverage_rel: float
    expected_m: float
    measured_m: float

    @property
    def ratio(self) -> float:
        return self.expected_m / self.measured_m if self.measured_m > 0 else float("nan")


def element_errors(
    predicted: Sequence[MapFeature], truth: Sequence[MapFeature]
) -> tuple[list[ElementError], int]:
    """The raw error of each predicted element with a ``sigma_abs_m`` (same frame as ``truth``),
    and the number of elements farther than ``UNMATCHED_M`` from every truth element of their type."""
    by_type: dict[object, np.ndarray] = {}
    out: list[ElementError] = []
    unmatched = 0
    for f in predicted:
        if SIGMA_ABS_PROPERTY not in f.properties or len(f.points_xy_world) < 2:
            continue
        if f.type not in by_type:
            chains = [np.asarray(t.points_xy_world, float) for t in truth if t.type == f.type]
            closed = [np.vstack([c, c[:1]]) if f.type.is_polygon else c for c in chains]
            by_type[f.type] = metrics._segments(closed)
        samples = metrics.sample_features([f], SAMPLE_STEP_M)
        error = float(
            np.median(metrics.distances_to_segments(samples, by_type[f.type], cap_m=2 * UNMATCHED_M))
        )
        if error > UNMATCHED_M:
            unmatched += 1
            continue
        xy = np.asarray(f.points_xy_world, float)
        closed_xy = np.vstack([xy, xy[:1]]) if f.type.is_polygon else xy
        out.append(
            ElementError(
                error_m=error,
                sigma_abs_m=float(f.properties[SIGMA_ABS_PROPERTY]),
                uncertainty_m=float(f.properties.get("uncertainty_m") or 0.0),
                length_m=float(np.linalg.norm(np.diff(closed_xy, axis=0), axis=1).sum()),
                passes=int(f.properties.get("support_trips") or 1),
            )
        )
    return out, unmatched


def calibration_row(name: str, errors: Sequence[ElementError], unmatched: int, trips: int) -> CalibrationRow:
    e = np.array([x.error_m for x in errors])
    sa = np.array([x.sigma_abs_m for x in errors])
    u = np.array([x.uncertainty_m for x in errors])
    w = np.array([x.length_m for x in errors])
    cert = tile_certificate(w, sa, u, [x.passes for x in errors], trips=trips, target_m=0.1)
    measured = float(np.sqrt(np.sum(w * e**2) / w.sum())) if len(e) and w.sum() > 0 else float("nan")
    return CalibrationRow(
        scenario=name,
        elements=len(errors),
        unmatched=unmatched,
        coverage_abs=float(np.mean(e <= COVERAGE_SIGMAS * sa)) if len(e) else float("nan"),
        coverage_rel=float(np.mean(e <= COVERAGE_SIGMAS * u)) if len(e) else float("nan"),
        expected_m=cert.expected_absolute_error_m,
        measured_m=measured,
    )


def calibrate_output(scenario_dir: str | Path, out_dir: str | Path) -> CalibrationRow:
    """The calibration of ``csr reconstruct``'s ``out_dir/map.geojson`` against the scenario's truth."""
    errors, unmatched, trips = scenario_errors(scenario_dir, out_dir)
    return calibration_row(Path(scenario_dir).name, errors, unmatched, trips)


def scenario_errors(scenario_dir: str | Path, out_dir: str | Path) -> tuple[list[ElementError], int, int]:
    """The element errors of ``out_dir/map.geojson`` against the scenario's truth, the false
    elements and the scenario's trips."""
    scenario_dir, out_dir = Path(scenario_dir), Path(out_dir)
    frame = read_scenario_meta(scenario_dir).frame
    truth = geo_features_to_local(read_map_geojson(scenario_dir / "truth" / "map.geojson"), frame)
    predicted = []
    for f in json.loads((out_dir / "map.geojson").read_text())["features"]:
        geometry = f["geometry"]
        if geometry["type"] not in ("LineString", "Polygon"):
            continue
        lonlat = np.asarray(
            geometry["coordinates"] if geometry["type"] == "LineString" else geometry["coordinates"][0], float
        )
        element_type = ElementType(f["properties"]["type"])
        if element_type.is_polygon:
            lonlat = lonlat[:-1]
        predicted.append(MapFeature(element_type, frame.to_local(lonlat), properties=f["properties"]))
    errors, unmatched = element_errors(predicted, truth)
    return errors, unmatched, len(list((scenario_dir / "trips").glob("*.json.gz")))


def calibration_table(rows: Sequence[CalibrationRow]) -> str:
    head = (
        "| scenario | elements | false | raw within 2 sigma_abs | raw within 2 uncertainty_m "
        "| certificate [m] | measured RMS [m] | ratio |\n| --- | ---: | ---: | ---: | ---: | ---: | ---: | ---: |"
    )
    lines = [
        f"| {r.scenario} | {r.elements} | {r.unmatched} | {100 * r.coverage_abs:.0f} % | {100 * r.coverage_rel:.0f} % "
        f"| {r.expected_m:.3f} | {r.measured_m:.3f} | {r.ratio:.2f} |"
        for r in rows
    ]
    return "\n".join([head, *lines])
