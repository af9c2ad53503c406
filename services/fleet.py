"""A fleet and a map team talking to a running service over HTTP (what ``csr demo`` and the service
benchmark do): upload a scenario's trips, have them processed, and fetch the results in the
scenario output format (contract section 4: ``poses/<key>.csv`` and ``map.geojson``) so that the
same evaluator scores the service and ``csr reconstruct``."""

from __future__ import annotations

import gzip
import time
from collections.abc import Callable
from pathlib import Path

import httpx
import numpy as np
import orjson
from tqdm import tqdm

from csr_core import upload_binary
from csr_core.scenario import POSES_CSV_HEADER, list_trip_files
from csr_core.upload_binary import EncodeOptions

ProgressFn = Callable[[str], None]


class ServiceError(RuntimeError):
    """The service answered something the fleet did not expect (status and body in the message)."""


def _check(response: httpx.Response, *expected: int) -> httpx.Response:
    if response.status_code not in expected:
        raise ServiceError(
            f"{response.request.method} {response.request.url.path}: "
            f"{response.status_code} {response.text[:500]}"
        )
    return response


BUSY_ATTEMPTS = 5  # tries of a call the service answers 503 (its database busy or unreachable)
BUSY_WAIT_MAX_S = 30.0  # the longest Retry-After honoured between two tries


class RetryBusy(httpx.BaseTransport):
    """Sends a call again after the ``Retry-After`` of a 503, at most :data:`BUSY_ATTEMPTS` times
    (every call of the fleet is idempotent: an upload sent twice is the same trip)."""

    def __init__(self, inner: httpx.BaseTransport, attempts: int = BUSY_ATTEMPTS) -> None:
        self.inner, self.attempts = inner, attempts

    def handle_request(self, request: httpx.Request) -> httpx.Response:
        for _ in range(self.attempts - 1):
            response = self.inner.handle_request(request)
            if response.status_code != 503:
                return response
            response.close()
            time.sleep(_retry_after_s(response))
        return self.inner.handle_request(request)

    def close(self) -> None:
        self.inner.close()


def _retry_after_s(response: httpx.Response) -> float:
    try:
        return min(max(float(response.headers.get("Retry-After", "1")), 0.0), BUSY_WAIT_MAX_S)
    except ValueError:  # an HTTP date: not sent by this service
        return 1.0


def client_for(base_url: str, key: str, timeout_s: float = 120.0) -> httpx.Client:
    return httpx.Client(
        base_url=base_url,
        headers={"Authorization": f"Bearer {key}"},
        timeout=timeout_s,
        transport=RetryBusy(httpx.HTTPTransport()),
    )


def upload_scenario(
    client: httpx.Client,
    scenario_dir: str | Path,
    *,
    progress: bool = True,
    binary: EncodeOptions | None = None,
) -> dict[str, str]:
    """POST every trip of the scenario (file-name order, gzip as stored); ``{trip key: server id}``.
    With ``binary``, each trip is sent as the compact binary upload (``docs/upload-binary.md``)
    encoded with these options, gzip-compressed."""
    ids: dict[str, str] = {}
    files = list_trip_files(scenario_dir)
    for tf in tqdm(files, desc="upload", unit="trip", disable=not progress):
        body = Path(tf.path).read_bytes()
        headers = {"Content-Type": "application/json"}
        if str(tf.path).endswith(".gz"):
            headers["Content-Encoding"] = "gzip"
        if binary is not None:
            doc = orjson.loads(gzip.decompress(body) if body[:2] == b"\x1f\x8b" else body)
            body = gzip.compress(upload_binary.encode(doc, binary))
            headers = {"Content-Type": upload_binary.MEDIA_TYPE, "Content-Encoding": "gzip"}
        answer = _check(client.post("/v1/trips", content=body, headers=headers), 200, 202).json()
        ids[tf.key] = answer["id"]
    return ids


def wait_until_processed(
    client: httpx.Client,
    trip_ids: dict[str, str],
    *,
    timeout_s: float = 1800.0,
    progress: bool = True,
    poll_s: float = 1.0,
) -> dict[str, str]:
    """Wait until every trip is ingested, then ask for processing now (``POST /v1/process``, so that
    each tile takes all its trips in one batch; repeated while tiles are dirty) and wait until every
    trip is ``aligned`` or ``failed`` and no job is queued or running; ``{key: status}``."""
    deadline = time.monotonic() + timeout_s
    bar = tqdm(total=len(trip_ids), desc="process", unit="trip", disable=not progress)
    statuses: dict[str, str] = {}
    try:
        while True:
            statuses = {
                k: _check(client.get(f"/v1/trips/{i}"), 200).json()["status"] for k, i in trip_ids.items()
            }
            if "received" not in statuses.values():  # every upload ingested: its tiles are known
                _check(client.post("/v1/process"), 202)
            done = sum(s in ("aligned", "failed") for s in statuses.values())
            bar.n = done
            bar.refresh()
            summary = _check(client.get("/v1/jobs/summary"), 200).json()
            if (
                done == len(trip_ids)
                and summary["queued"] == 0
                and summary["running"] == 0
                and summary["dirty_tiles"] == 0
            ):
                return statuses
            if time.monotonic() > deadline:
                raise ServiceError(
                    f"not processed within {timeout_s:.0f} s: {summary}, "
                    f"{sum(s == 'processing' for s in statuses.values())} trips processing"
                )
            time.sleep(poll_s)
    finally:
        bar.close()


def download_results(
    client: httpx.Client,
    trip_ids: dict[str, str],
    out_dir: str | Path,
    bbox_lonlat: tuple[float, float, float, float],
) -> dict[str, int]:
    """The service's poses of every aligned trip and the map of ``bbox`` written like ``csr
    reconstruct``'s output; counts of what was written."""
    out = Path(out_dir)
    (out / "poses").mkdir(parents=True, exist_ok=True)
    written = 0
    for key, trip_id in trip_ids.items():
        response = client.get(f"/v1/trips/{trip_id}/poses")
        if response.status_code == 409:  # failed: left out, as the contract's coverage counts it
            continue
        frames = _check(response, 200).json()["frames"]
        rows = np.array([[f["t"], f["lat"], f["lon"], f["heading_deg"]] for f in frames], float).reshape(
            -1, 4
        )
        lines = [POSES_CSV_HEADER] + [f"{t!r},{lat!r},{lon!r},{h!r}" for t, lat, lon, h in rows.tolist()]
        (out / "poses" / f"{key}.csv").write_text("\n".join(lines) + "\n")
        written += 1
    bbox = ",".join(repr(v) for v in bbox_lonlat)
    geojson = _check(client.get("/v1/map", params={"bbox": bbox}), 200).json()
    (out / "map.geojson").write_bytes(orjson.dumps(geojson))
    return {"poses": written, "features": len(geojson.get("features", []))}


def scenario_bbox(scenario_dir: str | Path, margin_deg: float = 0.002) -> tuple[float, float, float, float]:
    """The bounding box of the scenario's trips' GNSS fixes, grown by ``margin_deg``."""
    from csr_core.scenario import load_trip

    lo = np.array([np.inf, np.inf])
    hi = -lo
    for tf in list_trip_files(scenario_dir):
        trip = load_trip(tf)
        fixes = trip.gnss_lonlat_deg[trip.has_fix]
        if len(fixes):
            lo, hi = np.minimum(lo, fixes.min(axis=0)), np.maximum(hi, fixes.max(axis=0))
    return (
        float(lo[0] - margin_deg),
        float(lo[1] - margin_deg),
        float(hi[0] + margin_deg),
        float(hi[1] + margin_deg),
    )
