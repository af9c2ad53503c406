"""``csr bench-upload-memory``: how much memory an upload takes in the server, per MB uploaded.

A ``csr serve`` of the embedded default (jobs left in the database: only the upload path runs in
it) receives one kind of upload at a time; before each, the process's peak resident memory is
reset (``/proc/<pid>/clear_refs``), after it ``VmHWM`` minus the resident memory at the reset is
the upload's peak. Kinds: a 1 km trip of the ingest benchmark, a trip of many small frames (no
elements: the most Python objects per byte), a gzip bomb (1 GiB of zeros), four bombs at once.
The ingest side (the job that decodes a stored upload) is measured in this process with
``tracemalloc``, the whole-tree decode it replaced beside it. Linux only.
"""

from __future__ import annotations

import argparse
import gzip
import sys
import zlib
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from typing import Any

MIB = 1024 * 1024
BOMB_INFLATED_MIB = 1024
TINY_FRAMES = 200_000


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("bench-upload-memory", help="the server's peak memory per upload, per MB uploaded")
    p.add_argument("--tiny-frames", type=int, default=TINY_FRAMES, help="frames of the small-frames trip")
    p.add_argument("--write", metavar="MARKDOWN", help="put the table into this file (BENCHMARKS.md)")
    p.set_defaults(func=_run)


def tiny_frame_trip(n_frames: int, *, trip_id: str = "tiny", vehicle_id: str = "veh-0001") -> dict[str, Any]:
    """A valid upload of ``n_frames`` frames at 10 Hz without elements (~140 bytes of JSON each)."""
    frames = [
        {
            "t": round(0.1 * i, 1),
            "gnss": {"lat": 48.1366 + 1e-7 * i, "lon": 11.579, "status": "single", "std_m": 1.5},
            "odom": {"x": round(0.1 * i, 1), "y": 0.0, "yaw": 0.0},
            "elements": [],
        }
        for i in range(n_frames)
    ]
    return {
        "schema_version": "1.0",
        "vehicle_id": vehicle_id,
        "trip_id": trip_id,
        "started_at": "2026-01-01T00:00:00Z",
        "frames": frames,
    }


def gzip_bomb(inflated_mib: int = BOMB_INFLATED_MIB) -> bytes:
    """``inflated_mib`` MiB of zeros, gzip-compressed (~1 KB per MiB)."""
    compressor = zlib.compressobj(9, zlib.DEFLATED, 16 + zlib.MAX_WBITS)
    zeros = bytes(MIB)
    return b"".join(compressor.compress(zeros) for _ in range(inflated_mib)) + compressor.flush()


def _status_kib(pid: int, field: str) -> int:
    with open(f"/proc/{pid}/status") as status:
        for line in status:
            if line.startswith(field + ":"):
                return int(line.split()[1])
    raise RuntimeError(f"no {field} in /proc/{pid}/status")


class PeakMemory:
    """The peak resident memory of a process (``VmHWM``) above its resident memory at ``reset``."""

    def __init__(self, pid: int) -> None:
        self.pid = pid
        self.base_kib = 0

    def reset(self) -> None:
        with open(f"/proc/{self.pid}/clear_refs", "w") as clear:
            clear.write("5")  # resets VmHWM to the current VmRSS
        self.base_kib = _status_kib(self.pid, "VmRSS")

    def rise_bytes(self) -> int:
        return (_status_kib(self.pid, "VmHWM") - self.base_kib) * 1024


@dataclass(frozen=True, slots=True)
class Row:
    case: str
    sent_bytes: int
    json_bytes: int  # decompressed size (for a bomb: what the limit lets it produce)
    statuses: str
    peak_rise_bytes: int

    @property
    def per_json_byte(self) -> float:
        return self.peak_rise_bytes / self.json_bytes


def _post(base_url: str, key: str, body: bytes) -> int:
    import httpx

    headers = {
        "Authorization": f"Bearer {key}",
        "Content-Type": "application/json",
        "Content-Encoding": "gzip",
    }
    return httpx.post(base_url + "/v1/trips", content=body, headers=headers, timeout=300).status_code


def _measure(peak: PeakMemory, post, case: str, bodies: list[bytes], json_bytes: int) -> Row:
    peak.reset()
    with ThreadPoolExecutor(len(bodies)) as pool:
        statuses = sorted(pool.map(post, bodies))
    return Row(case, sum(map(len, bodies)), json_bytes, ", ".join(map(str, statuses)), peak.rise_bytes())


def measure_server(tiny_frames: int) -> tuple[list[Row], int]:
    """The rows of the server, and its ``CSR_MAX_DECOMPRESSED_BYTES``."""
    import orjson

    from services.cli.bench_ingest import straight_trip
    from services.local_deployment import LocalDeployment
    from services.settings import Settings

    limit = Settings().max_decompressed_bytes
    trip = orjson.dumps(straight_trip(vehicle_id="veh-0001", trip_id="km", length_m=1000.0))
    tiny = orjson.dumps(tiny_frame_trip(tiny_frames))
    bomb = gzip_bomb()
    with LocalDeployment("embedded", extra_env={"CSR_EMBEDDED_WORKERS": "0"}) as dep:
        peak = PeakMemory(dep.server_pid)

        def post(body: bytes) -> int:
            return _post(dep.base_url, dep.admin_key, body)

        # the first requests import and allocate what every later one reuses
        post(gzip.compress(orjson.dumps(tiny_frame_trip(1000, trip_id="warm-up"))))
        post(gzip.compress(orjson.dumps(straight_trip(vehicle_id="veh-0001", trip_id="warm-up-km"))))
        rows = [
            _measure(peak, post, "1 km trip (4 elements per frame)", [gzip.compress(trip)], len(trip)),
            _measure(peak, post, f"{tiny_frames} frames without elements", [gzip.compress(tiny)], len(tiny)),
            _measure(peak, post, "gzip bomb (1 GiB of zeros)", [bomb], limit),
            _measure(peak, post, "4 gzip bombs at once", [bomb] * 4, limit),
        ]
    return rows, limit


def measure_ingest_decode(tiny_frames: int) -> tuple[float, float]:
    """Peak traced bytes per frame of decoding the small-frames trip: frame batches, whole tree."""
    import tracemalloc

    import orjson

    from csr_core.upload import decode_trip
    from csr_core.upload_frames import decode_upload_json

    body = orjson.dumps(tiny_frame_trip(tiny_frames))
    peaks = []
    for decode in (decode_upload_json, lambda b: decode_trip(orjson.loads(b))):
        tracemalloc.start()
        decode(body)
        peaks.append(tracemalloc.get_traced_memory()[1] / tiny_frames)
        tracemalloc.stop()
    return peaks[0], peaks[1]


def format_section(rows: list[Row], limit: int, ingest: tuple[float, float], tiny_frames: int) -> str:
    lines = [
        "Peak resident memory of `csr serve` (embedded default, jobs left in the database) above its resident "
        "memory just before each upload (`VmHWM` after resetting it through `/proc/<pid>/clear_refs`), default "
        f"limits (`CSR_MAX_DECOMPRESSED_BYTES` {limit // MIB} MiB, `CSR_MAX_UPLOAD_BYTES_IN_FLIGHT` the same). "
        "For a bomb, the decompressed size is the limit (it is refused there). "
        "Reproduce: `csr bench-upload-memory --write BENCHMARKS.md` (~3 min).",
        "",
        "| upload | sent MB | decompressed MB | answers | peak rise MB | peak / decompressed size |",
        "| --- | ---: | ---: | --- | ---: | ---: |",
    ]
    for r in rows:
        lines.append(
            f"| {r.case} | {r.sent_bytes / 1e6:.2f} | {r.json_bytes / 1e6:.1f} | {r.statuses} | "
            f"{r.peak_rise_bytes / 1e6:.0f} | {r.per_json_byte:.2f} |"
        )
    single = [r for r in rows if "4 gzip" not in r.case]
    four = next(r for r in rows if "4 gzip" in r.case)
    met_each = all(r.per_json_byte <= 4 for r in single)
    lines += [
        "",
        f"Ingest (the job decoding a stored upload), {tiny_frames} frames without elements, peak traced bytes "
        f"per frame: {ingest[0]:.0f} by frame batches, {ingest[1]:.0f} for `orjson.loads` and the whole tree.",
        "",
        f"Targets: an upload's peak <= 4x its decompressed size: {'met' if met_each else 'NOT met'}; "
        f"4 bombs at once raise the peak by <= 300 MB: {'met' if four.peak_rise_bytes <= 300e6 else 'NOT met'} "
        f"({four.peak_rise_bytes / 1e6:.0f} MB).",
    ]
    return "\n".join(lines)


def _run(args: argparse.Namespace) -> int:
    from services.cli.bench_common import publish

    if not sys.platform.startswith("linux"):
        print("csr bench-upload-memory reads /proc: Linux only", file=sys.stderr)
        return 2
    rows, limit = measure_server(args.tiny_frames)
    section = format_section(rows, limit, measure_ingest_decode(args.tiny_frames), args.tiny_frames)
    publish(section, args.write, "upload-memory", "bench-upload-memory")
    return 0
