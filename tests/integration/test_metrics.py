"""``/metrics`` as Prometheus scrapes it: HTTP series by route template, tile answers by source,
process series, no series per tile, a text that prometheus_client's parser and ``promtool check
metrics`` accept, and the metrics key of ``CSR_METRICS_KEY_FILE``."""

from __future__ import annotations

import secrets
import subprocess
import uuid

import pytest
from prometheus_client.parser import text_string_to_metric_families
from prometheus_client.samples import Sample

from tests.integration.conftest import Deployment, moving_trip, unique_trip, wait_until

pytestmark = pytest.mark.integration

# every metric the API reference names (README, "GET /metrics"), with its labels as they were
CONTRACT_SERIES = {
    "csr_uploads_total": {"result"},
    "csr_upload_bytes_total": {"form"},
    "csr_upload_rejects_total": {"reason"},
    "csr_upload_duration_seconds_bucket": {"le"},
    "csr_queue_depth": {"queue"},
    "csr_jobs": {"queue", "state"},
    "csr_dirty_tiles": set(),
    "csr_job_duration_seconds_bucket": {"kind", "le"},
}


def _samples(text: str) -> list[Sample]:
    return [s for family in text_string_to_metric_families(text) for s in family.samples]


def _value(samples: list[Sample], name: str, **labels: str) -> float:
    return sum(s.value for s in samples if s.name == name and labels.items() <= s.labels.items())


def test_metrics_name_route_templates_process_and_no_tile_labels(deployment: Deployment):
    missing_trip = str(uuid.uuid4())
    deployment.upload(b"{oops")
    deployment.upload(unique_trip())
    deployment.wait_idle()  # its ingest job has finished (and failed: the example cannot be oriented)
    with deployment.admin() as http:
        assert http.get(f"/v1/trips/{missing_trip}").status_code == 404
        assert http.get(f"/no/such/path/{missing_trip}").status_code == 404
        # the deployment is shared: other tests' tile calls (401s, 422s) are counted too
        start = _samples(http.get("/metrics").text)
        for _ in range(3):
            assert http.get("/v1/tiles/16/34322/22950.mvt").status_code in (200, 204)
        assert http.put("/healthz").status_code == 405
        before = _samples(http.get("/metrics").text)
        assert http.get(f"/v1/trips/{missing_trip}").status_code == 404
        text = http.get("/metrics").text
    samples = _samples(text)

    requests = [s for s in samples if s.name == "csr_http_requests_total"]
    routes = {s.labels["route"] for s in requests}
    assert {"/v1/trips", "/v1/trips/{trip_pk}", "/v1/tiles/{z}/{x}/{y}.mvt", "unmatched"} <= routes, routes
    assert not any(missing_trip in str(s.labels) for s in samples), "a raw path became a label"
    # a bounded set: the deployment is shared with other tests, whose methods are counted too
    assert {s.labels["method"] for s in requests} <= {
        "GET",
        "HEAD",
        "POST",
        "PUT",
        "PATCH",
        "DELETE",
        "OPTIONS",
        "other",
    }
    assert {"GET", "POST", "PUT"} <= {s.labels["method"] for s in requests}
    one_more = _value(samples, "csr_http_requests_total", route="/v1/trips/{trip_pk}", status="404")
    assert (
        one_more == _value(before, "csr_http_requests_total", route="/v1/trips/{trip_pk}", status="404") + 1
    )
    assert _value(samples, "csr_http_requests_total", route="/v1/trips", method="POST", status="400") >= 1
    assert _value(samples, "csr_http_requests_total", route="/healthz", method="PUT", status="405") >= 1
    tiles_timed = _value(
        samples, "csr_http_request_duration_seconds_count", route="/v1/tiles/{z}/{x}/{y}.mvt", method="GET"
    )
    assert tiles_timed >= 3
    # every tile answer counted once, by where its body came from
    tile_route = "/v1/tiles/{z}/{x}/{y}.mvt"
    served = _value(samples, "csr_tile_requests_total") - _value(start, "csr_tile_requests_total")
    answered = _value(samples, "csr_http_requests_total", route=tile_route) - _value(
        start, "csr_http_requests_total", route=tile_route
    )
    assert served == answered == 3, (served, answered)

    names = {s.name for s in samples}
    assert {"process_cpu_seconds_total", "process_resident_memory_bytes", "process_open_fds"} <= names
    assert {"python_info", "csr_published_tiles", "csr_map_version", "csr_tiles"} <= names
    assert "csr_upload_to_published_seconds_count" in names
    for name, labels in CONTRACT_SERIES.items():
        found = [s for s in samples if s.name == name]
        assert found and all(set(s.labels) == labels for s in found), (name, found[:3])
    assert not any("tile" in s.labels for s in samples), "a label per tile"

    check = subprocess.run(["promtool", "check", "metrics"], input=text, capture_output=True, text=True)
    assert check.returncode == 0, check.stdout + check.stderr


def test_the_metrics_key_opens_metrics_only(make_isolated, tmp_path):
    key_file = tmp_path / "metrics.key"
    scrape_key = secrets.token_hex(24)
    key_file.write_text(scrape_key + "\n")
    dep = make_isolated("embedded", CSR_METRICS_KEY_FILE=str(key_file))
    dep.start_server()
    with dep.client(scrape_key) as scraper:
        assert scraper.get("/metrics").status_code == 200
        summary = scraper.get("/v1/jobs/summary")
        assert summary.status_code == 401 and summary.json()["error"] == "unauthorized"
    with dep.client(scrape_key[:-1]) as wrong:
        assert wrong.get("/metrics").status_code == 401
    with dep.admin() as http:  # reader and admin keys open it as before
        assert http.get("/metrics").status_code == 200


def test_a_metrics_key_file_that_cannot_be_read_stops_the_start(make_isolated, tmp_path):
    dep = make_isolated("embedded", CSR_METRICS_KEY_FILE=str(tmp_path / "absent.key"))
    with pytest.raises(AssertionError, match="CSR_METRICS_KEY_FILE"):
        dep.start_server()


def test_upload_to_published_latency_counts_a_trip_in_the_map(make_isolated):
    dep = make_isolated("embedded", CSR_QUIET_PERIOD_S="1")
    dep.start_server()
    trip_pk = dep.upload(moving_trip()).raise_for_status().json()["id"]
    with dep.admin() as http:
        wait_until(
            lambda: http.get(f"/v1/trips/{trip_pk}").json()["status"] in ("aligned", "failed"),
            timeout_s=300,
            what="the trip's ingest and tile jobs",
        )
        dep.wait_idle(timeout_s=300)  # the merge job after the tile job
        assert http.get(f"/v1/trips/{trip_pk}").json()["status"] == "aligned"
        samples = _samples(http.get("/metrics").text)
    live = dep.scalar("SELECT count(*) FROM tile_heads WHERE live_version_id IS NOT NULL")
    assert live >= 1 and _value(samples, "csr_published_tiles") == live
    assert _value(samples, "csr_upload_to_published_seconds_count") == 1
    received, published = dep.rows(
        "SELECT min(t.received_at), max(v.created_at) FROM trips t, tile_versions v"
    )[0]
    assert 0 < _value(samples, "csr_upload_to_published_seconds_sum") <= _seconds(published, received) + 1e-3


def _seconds(later: object, earlier: object) -> float:
    from datetime import datetime

    def parse(at: object) -> datetime:
        return at if isinstance(at, datetime) else datetime.fromisoformat(str(at))

    return (parse(later) - parse(earlier)).total_seconds()
