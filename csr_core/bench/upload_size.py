"""Upload bytes per km of the JSON and the compact binary upload (``csr bench-upload-size``), and
whether the single-trip reconstruction from the decoded binary equals the one from the JSON.

Kilometres are the length of each trip's true poses (``truth/poses``); bytes are the body as
sent (gzip at level 6 where compressed). The reconstruction is ``reconstruct_trip`` (what the
ingest job runs) in the region frame of the trip's first fix, from the JSON document and from
each binary variant's decoded document; ATE is the raw RMSE of its positions against the true
poses (no alignment), the offset the largest distance between its poses and the JSON's; the
trip's instances (what alignment and fusion receive) are scored against the true map as contract
section 6 scores a map (mCD, no alignment)."""

from __future__ import annotations

import gzip
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import orjson

from csr_core import upload_binary
from csr_core.geo import LocalFrame, region_frame_for
from csr_core.metrics import map_scores
from csr_core.scenario import geo_features_to_local, list_trip_files, read_map_geojson, read_poses_csv
from csr_core.single_trip import reconstruct_trip
from csr_core.types import MapFeature, TripReconstruction
from csr_core.upload import decode_trip, validate_upload, validate_upload_json
from csr_core.upload_binary import Decimals, EncodeOptions

GZIP_LEVEL = 6


@dataclass(frozen=True, slots=True)
class UploadVariant:
    name: str
    options: EncodeOptions | None  # None: the contract's JSON
    gzipped: bool


VARIANTS = (
    UploadVariant("JSON", None, False),
    UploadVariant("JSON, gzip", None, True),
    UploadVariant("binary", EncodeOptions(), False),
    UploadVariant("binary, gzip", EncodeOptions(), True),
    UploadVariant("binary, 1 cm points, gzip", EncodeOptions(decimals=Decimals(point_m=2)), True),
    UploadVariant("binary, keyframes every 5.5 m, gzip", EncodeOptions(keyframe_spacing_m=5.5), True),
    UploadVariant(
        "binary, keyframes every 5.5 m, 1 cm points, gzip",
        EncodeOptions(decimals=Decimals(point_m=2), keyframe_spacing_m=5.5),
        True,
    ),
)


@dataclass(frozen=True, slots=True)
class SizeRow:
    variant: str
    bytes_total: int
    km: float

    @property
    def kb_per_km(self) -> float:
        return self.bytes_total / 1000.0 / self.km


@dataclass(frozen=True, slots=True)
class ReconstructionRow:
    variant: str
    trip: str
    ate_m: float  # raw RMSE against the true poses
    max_offset_from_json_m: float
    n_instances: int
    instances_mcd_m: float  # the trip's instances against the true map


def body_bytes(doc: dict[str, Any], json_body: bytes, variant: UploadVariant) -> bytes:
    body = json_body if variant.options is None else upload_binary.encode(doc, variant.options)
    return gzip.compress(body, compresslevel=GZIP_LEVEL) if variant.gzipped else body


def _true_track_m(scenario_dir: Path, key: str) -> tuple[np.ndarray, float]:
    truth = read_poses_csv(scenario_dir / "truth" / "poses" / f"{key}.csv")
    frame = region_frame_for(truth.lonlat_deg[0])
    xy = frame.to_local(truth.lonlat_deg)
    return truth.lonlat_deg, float(np.sum(np.linalg.norm(np.diff(xy, axis=0), axis=1)))


def _reconstruct(doc: dict[str, Any]) -> tuple[TripReconstruction, LocalFrame]:
    trip = decode_trip(doc)
    region = region_frame_for(trip.gnss_lonlat_deg[trip.has_fix][0])
    return reconstruct_trip(trip, region), region


def _instances_mcd_m(recon: TripReconstruction, truth: Sequence[MapFeature], true_xy: np.ndarray) -> float:
    pred = [
        MapFeature(type=i.type, points_xy_world=i.points_xy_world, style=i.style) for i in recon.instances
    ]
    return map_scores(pred, truth, true_xy).mcd


def measure(
    scenario_dir: str | Path, *, n_reconstruct: int = 2
) -> tuple[list[SizeRow], list[ReconstructionRow]]:
    """Bytes per km of every variant over the scenario's trips; the reconstruction comparison
    on the first ``n_reconstruct`` trips."""
    scenario_dir = Path(scenario_dir)
    totals = dict.fromkeys((v.name for v in VARIANTS), 0)
    km = 0.0
    rows: list[ReconstructionRow] = []
    for index, trip_file in enumerate(list_trip_files(scenario_dir)):
        json_body = gzip.decompress(trip_file.path.read_bytes())
        doc = validate_upload_json(json_body)
        true_lonlat, length_m = _true_track_m(scenario_dir, trip_file.key)
        km += length_m / 1000.0
        for variant in VARIANTS:
            totals[variant.name] += len(body_bytes(doc, json_body, variant))
        if index >= n_reconstruct:
            continue
        reference, region = _reconstruct(orjson.loads(json_body))
        true_xy = region.to_local(true_lonlat)
        truth = geo_features_to_local(read_map_geojson(scenario_dir / "truth" / "map.geojson"), region)
        for variant in VARIANTS:
            if not variant.gzipped:
                continue
            recon = reference
            if variant.options is not None:
                decoded = upload_binary.decode(upload_binary.encode(doc, variant.options))
                recon, _ = _reconstruct(validate_upload(decoded))
            xy = recon.poses_xyyaw_world[:, :2]
            rows.append(
                ReconstructionRow(
                    variant=variant.name,
                    trip=trip_file.key,
                    ate_m=float(np.sqrt(np.mean(np.sum((xy - true_xy) ** 2, axis=1)))),
                    max_offset_from_json_m=float(
                        np.max(np.linalg.norm(xy - reference.poses_xyyaw_world[:, :2], axis=1))
                    ),
                    n_instances=len(recon.instances),
                    instances_mcd_m=_instances_mcd_m(recon, truth, true_xy),
                )
            )
    return [SizeRow(name, total, km) for name, total in totals.items()], rows


def markdown(sizes: list[SizeRow], reconstructions: list[ReconstructionRow]) -> str:
    json_gzip = next(r for r in sizes if r.variant == "JSON, gzip")
    lines = [
        "| upload | KB per km | vs gzip JSON |",
        "| --- | ---: | ---: |",
        *(
            f"| {r.variant} | {r.kb_per_km:.0f} | {r.bytes_total / json_gzip.bytes_total:.2f} |"
            for r in sizes
        ),
        "",
        "| upload | trip | single-trip ATE [m] | largest pose offset from the JSON's [m] "
        "| instances | instances' mCD [m] |",
        "| --- | --- | ---: | ---: | ---: | ---: |",
        *(
            f"| {r.variant} | {r.trip} | {r.ate_m:.3f} | {r.max_offset_from_json_m:.4f} "
            f"| {r.n_instances} | {r.instances_mcd_m:.3f} |"
            for r in reconstructions
        ),
    ]
    return "\n".join(lines)
