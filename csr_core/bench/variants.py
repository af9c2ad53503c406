"""Foreign fleets: contract-valid uploads that our simulator does not write (``csr bench-variants``).

Outside evaluators run ``csr reconstruct`` on scenario folders from their own simulators and
logs (contract section 5). What the contract allows, ours never produces: no ``std_m`` or one
off by a factor, no course heading, fixes repeated between receiver epochs, lower or lossy frame rates, an
odometry frame that does not start at the origin, times that do not start at zero, a region far
from central Europe, coarse polylines, detector scores and tracker ids, no ``sensor_setup``, a
perception stack without some element types, a GNSS antenna away from the vehicle frame. Each variant
here rewrites a simulated scenario folder into such a fleet (uploads, truth poses and truth map
kept consistent), so that the whole command can be run on it and scored against the same truth
as the original.

A variant is a pure rewrite of one trip upload (a JSON document, contract section 1) plus, where
frames are dropped or coordinates moved, the same rewrite of the truth. Nothing here knows the
pipeline: a variant that makes ``csr reconstruct`` fail or lose accuracy is a finding.
"""

from __future__ import annotations

import copy
import gzip
import json
import shutil
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from csr_core.geo import LocalFrame
from csr_core.scenario import read_scenario_meta


@dataclass(frozen=True)
class Variant:
    """``rewrite_trip(doc, rng)`` returns the new upload and the indices of the frames it kept
    (``None``: all); ``origin_latlon``: move the whole scenario there (uploads, truth, map);
    ``antenna_forward_left_m``: move every fix to a GNSS antenna mounted there (true headings)."""

    name: str
    what: str
    rewrite_trip: Callable[[dict, np.random.Generator], tuple[dict, np.ndarray | None]] = lambda doc, rng: (
        doc,
        None,
    )
    origin_latlon: tuple[float, float] | None = None
    #: the GNSS antenna this far ahead of and left of the vehicle frame's origin (metres): the fixes
    #: are the antenna's, the odometry and perception the vehicle frame's
    antenna_forward_left_m: tuple[float, float] | None = None
    #: a known gap of the pipeline that this variant shows (why it may not hold), "" for none
    gap: str = ""


def _without_gnss_field(name: str) -> Callable[[dict, np.random.Generator], tuple[dict, None]]:
    def rewrite(doc: dict, rng: np.random.Generator) -> tuple[dict, None]:
        for f in doc["frames"]:
            f["gnss"].pop(name, None)
        return doc, None

    return rewrite


def _every_nth_frame(n: int) -> Callable[[dict, np.random.Generator], tuple[dict, np.ndarray]]:
    def rewrite(doc: dict, rng: np.random.Generator) -> tuple[dict, np.ndarray]:
        keep = np.arange(0, len(doc["frames"]), n)
        doc["frames"] = [doc["frames"][k] for k in keep]
        return doc, keep

    return rewrite


def _frames_dropped(doc: dict, rng: np.random.Generator) -> tuple[dict, np.ndarray]:
    """A logger that loses frames: a random tenth of them, and three gaps of 2 s."""
    n = len(doc["frames"])
    keep = rng.random(n) >= 0.1
    for start in rng.integers(1, max(n - 20, 2), size=3):
        keep[start : start + 20] = False
    keep[[0, -1]] = True
    idx = np.flatnonzero(keep)
    doc["frames"] = [doc["frames"][k] for k in idx]
    return doc, idx


def _gnss_held(period_s: float) -> Callable[[dict, np.random.Generator], tuple[dict, None]]:
    """A receiver slower than the frames: each frame repeats the last epoch's fix (a
    zero-order hold, as logs that copy the latest fix into every camera frame do)."""

    def rewrite(doc: dict, rng: np.random.Generator) -> tuple[dict, None]:
        last, last_t = None, -np.inf
        for f in doc["frames"]:
            if f["t"] - last_t >= period_s - 1e-6 or last is None:
                last, last_t = copy.deepcopy(f["gnss"]), f["t"]
            else:
                f["gnss"] = copy.deepcopy(last)
        return doc, None

    return rewrite


def _odometry_elsewhere(doc: dict, rng: np.random.Generator) -> tuple[dict, None]:
    """The odometry frame rotated and moved (only differences between frames are meaningful)."""
    yaw0 = float(rng.uniform(-np.pi, np.pi))
    x0, y0 = rng.uniform(-5000.0, 5000.0, size=2)
    c, s = np.cos(yaw0), np.sin(yaw0)
    for f in doc["frames"]:
        x, y, yaw = f["odom"]["x"], f["odom"]["y"], f["odom"]["yaw"]
        f["odom"] = {"x": x0 + c * x - s * y, "y": y0 + s * x + c * y, "yaw": yaw + yaw0}
    return doc, None


def _odometry_yaw_continuous(doc: dict, rng: np.random.Generator) -> tuple[dict, None]:
    """Odometry yaw integrated without wrapping (ours wraps into [-pi, pi)): it runs past pi
    as the vehicle turns, as many dead-reckoning logs store it."""
    yaw = np.unwrap([f["odom"]["yaw"] for f in doc["frames"]])
    for f, y in zip(doc["frames"], yaw, strict=True):
        f["odom"]["yaw"] = float(y)
    return doc, None


def _time_offset(doc: dict, rng: np.random.Generator) -> tuple[dict, None]:
    """Frame times that start well after ``started_at`` (the contract only asks t >= 0)."""
    dt = float(rng.uniform(100.0, 1000.0))
    for f in doc["frames"]:
        f["t"] = f["t"] + dt
    return doc, None


def _detector_extras(doc: dict, rng: np.random.Generator) -> tuple[dict, None]:
    """Scores and on-vehicle tracker ids on every element, every divider's style unknown, no
    ``sensor_setup``: what a production perception stack might send instead of ours."""
    doc.pop("sensor_setup", None)
    for f in doc["frames"]:
        for e in f["elements"]:
            e["score"] = round(float(rng.uniform(0.3, 1.0)), 3)
            e["track_id"] = int(rng.integers(0, 1_000_000))
            if e["type"] == "lane_divider":
                e["style"] = "unknown"
    return doc, None


def _coarse_polylines(doc: dict, rng: np.random.Generator) -> tuple[dict, None]:
    """Every third vertex of each line (and its last): a detector with sparser output points."""
    for f in doc["frames"]:
        for e in f["elements"]:
            if e["type"] in ("crosswalk", "road_marking"):
                continue
            pts = e["points"]
            if len(pts) > 3:
                e["points"] = pts[::3] + ([pts[-1]] if (len(pts) - 1) % 3 else [])
    return doc, None


def _without_types(*types: str) -> Callable[[dict, np.random.Generator], tuple[dict, None]]:
    """A perception stack that does not report these element types."""

    def rewrite(doc: dict, rng: np.random.Generator) -> tuple[dict, None]:
        for f in doc["frames"]:
            f["elements"] = [e for e in f["elements"] if e["type"] not in types]
        return doc, None

    return rewrite


def _std_scaled(factor: float) -> Callable[[dict, np.random.Generator], tuple[dict, None]]:
    """The receiver's ``std_m`` off by ``factor`` (a consumer receiver that claims centimetres,
    or one that hedges to metres); the fixes themselves unchanged."""

    def rewrite(doc: dict, rng: np.random.Generator) -> tuple[dict, None]:
        for f in doc["frames"]:
            if "std_m" in f["gnss"]:
                f["gnss"]["std_m"] = round(f["gnss"]["std_m"] * factor, 4) or 1e-4
        return doc, None

    return rewrite


def _status_single(doc: dict, rng: np.random.Generator) -> tuple[dict, None]:
    """Every fix reported as a single-point fix (a receiver that never reports RTK or DGPS)."""
    for f in doc["frames"]:
        if f["gnss"]["status"] != "none":
            f["gnss"]["status"] = "single"
    return doc, None


VARIANTS: dict[str, Variant] = {
    v.name: v
    for v in (
        Variant("original", "the simulated fleet as written"),
        Variant("no_std", "no receiver std_m on any fix", _without_gnss_field("std_m")),
        Variant("no_heading", "no course heading on any fix", _without_gnss_field("heading_deg")),
        Variant(
            "gnss_1hz_held", "the receiver at 1 Hz, its fix repeated on the 9 frames between", _gnss_held(1.0)
        ),
        Variant("frames_5hz", "every second frame (5 Hz)", _every_nth_frame(2)),
        Variant("frames_2hz", "every fifth frame (2 Hz)", _every_nth_frame(5)),
        Variant("frames_dropped", "a random tenth of the frames lost, and three 2 s gaps", _frames_dropped),
        Variant("odom_elsewhere", "odometry frame rotated and moved kilometres", _odometry_elsewhere),
        Variant("odom_yaw_continuous", "odometry yaw not wrapped into [-pi, pi)", _odometry_yaw_continuous),
        Variant("t_offset", "frame times start 100-1000 s after started_at", _time_offset),
        Variant(
            "detector_extras", "scores, tracker ids, divider style unknown, no sensor_setup", _detector_extras
        ),
        Variant("coarse_polylines", "every third vertex of each line", _coarse_polylines),
        Variant("std_overconfident", "every std_m a tenth of the simulator's honest one", _std_scaled(0.1)),
        Variant("std_pessimistic", "every std_m five times the honest one", _std_scaled(5.0)),
        Variant("status_single", "every fix reported as status single", _status_single),
        Variant(
            "antenna_ahead",
            "GNSS antenna 1.5 m ahead of the vehicle frame (the roof, not the rear axle)",
            antenna_forward_left_m=(1.5, 0.0),
            gap="no antenna lever arm is estimated: trips driving a road in opposite directions start 3 m apart "
            "along it (docs/single-trip.md)",
        ),
        Variant(
            "no_centerline",
            "a perception stack without centrelines (MapTR's classes)",
            _without_types("centerline"),
        ),
        Variant(
            "no_markings",
            "no stop lines, crosswalks or road markings perceived",
            _without_types("stop_line", "crosswalk", "road_marking"),
        ),
        Variant("southern_west", "the fleet moved to 33.4 S 70.6 W", origin_latlon=(-33.45, -70.66)),
        Variant("far_north", "the fleet moved to 69.6 N 18.9 E", origin_latlon=(69.65, 18.96)),
    )
}


def _move_lonlat(lonlat_deg: np.ndarray, src: LocalFrame, dst: LocalFrame) -> np.ndarray:
    """The same local plane position about another origin (a fleet moved, not re-projected)."""
    return dst.to_lonlat(src.to_local(lonlat_deg))


def _move_geometry(coords, src: LocalFrame, dst: LocalFrame):
    """GeoJSON coordinates (a position, a line, or nested rings) moved as :func:`_move_lonlat`."""
    a = np.asarray(coords, float)
    if a.ndim == 1:
        return [float(v) for v in _move_lonlat(a[None, :2], src, dst)[0]]
    if a.ndim == 2:
        return _move_lonlat(a[:, :2], src, dst).tolist()
    return [_move_geometry(c, src, dst) for c in coords]


def write_variant(source: Path, out: Path, variant: Variant, seed: int = 0) -> Path:
    """``source`` (a scenario folder, contract section 5) rewritten by ``variant`` into ``out``
    (replaced if it exists); returns ``out``."""
    if out.exists():
        shutil.rmtree(out)
    (out / "trips").mkdir(parents=True)
    (out / "truth" / "poses").mkdir(parents=True)
    scenario = json.loads((source / "scenario.json").read_text())
    src = read_scenario_meta(source).frame
    dst = src
    if variant.origin_latlon is not None:
        lat, lon = variant.origin_latlon
        scenario["origin"] = {"lat": lat, "lon": lon}
        dst = LocalFrame(lat, lon)
    scenario["name"] = f"{scenario.get('name', source.name)}-{variant.name}"
    (out / "scenario.json").write_text(json.dumps(scenario, indent=2))
    rng = np.random.default_rng(seed)
    for path in sorted((source / "trips").glob("*.json.gz")):
        doc = json.loads(gzip.decompress(path.read_bytes()))
        first_t = float(doc["frames"][0]["t"])
        doc, keep = variant.rewrite_trip(doc, rng)
        key = path.name.removesuffix(".json.gz")
        truth = np.loadtxt(source / "truth" / "poses" / f"{key}.csv", delimiter=",", skiprows=1, ndmin=2)
        truth = truth if keep is None else truth[keep]  # t, lat, lon, heading_deg per uploaded frame
        if variant.antenna_forward_left_m is not None:
            _move_to_antenna(doc, truth[:, 3], src, variant.antenna_forward_left_m)
        if dst is not src:
            _set_fixes(doc, _move_lonlat(_fixes(doc), src, dst))
        (out / "trips" / path.name).write_bytes(gzip.compress(json.dumps(doc).encode()))
        _write_truth_poses(
            truth, out / "truth" / "poses" / f"{key}.csv", src, dst, t_shift=doc["frames"][0]["t"] - first_t
        )
    truth_map = json.loads((source / "truth" / "map.geojson").read_text())
    if dst is not src:
        for feat in truth_map["features"]:
            feat["geometry"]["coordinates"] = _move_geometry(feat["geometry"]["coordinates"], src, dst)
    (out / "truth" / "map.geojson").write_text(json.dumps(truth_map))
    return out


def _fixes(doc: dict) -> np.ndarray:
    """``(N, 2)`` every frame's fix, lon and lat (meaningless where the status is none)."""
    return np.array([[f["gnss"]["lon"], f["gnss"]["lat"]] for f in doc["frames"]])


def _set_fixes(doc: dict, lonlat_deg: np.ndarray) -> None:
    for f, (lon, lat) in zip(doc["frames"], lonlat_deg, strict=True):
        f["gnss"]["lon"], f["gnss"]["lat"] = round(float(lon), 9), round(float(lat), 9)


def _move_to_antenna(
    doc: dict, heading_deg: np.ndarray, frame: LocalFrame, forward_left_m: tuple[float, float]
) -> None:
    """Every fix moved by the antenna's offset, turned by the frame's true heading (degrees
    clockwise from north, one per frame of ``doc``)."""
    heading = np.radians(heading_deg)
    forward = np.column_stack([np.sin(heading), np.cos(heading)])
    left = np.column_stack([-forward[:, 1], forward[:, 0]])
    offset = forward_left_m[0] * forward + forward_left_m[1] * left
    _set_fixes(doc, frame.to_lonlat(frame.to_local(_fixes(doc)) + offset))


def _write_truth_poses(
    rows: np.ndarray, dst_csv: Path, src: LocalFrame, dst: LocalFrame, t_shift: float
) -> None:
    """The truth rows (t, lat, lon, heading_deg) of the kept frames, shifted in time and moved."""
    rows = rows.copy()
    rows[:, 0] += t_shift
    if dst is not src:
        moved = _move_lonlat(rows[:, [2, 1]], src, dst)
        rows[:, 1], rows[:, 2] = moved[:, 1], moved[:, 0]
    lines = ["t,lat,lon,heading_deg"] + [f"{t:.3f},{lat:.9f},{lon:.9f},{h:.3f}" for t, lat, lon, h in rows]
    dst_csv.write_text("\n".join(lines) + "\n")


SECTION = "variants"
#: a variant *holds* when its aligned ATE and mCD stay within this factor of the original's, plus
#: ``HOLD_SLACK_M`` (two runs of one fleet differ by a few millimetres; a variant that drops
#: frames or fields has less to work with, but a foreign fleet must not lose half its accuracy)
HOLD_FACTOR = 1.25
HOLD_SLACK_M = 0.02


@dataclass(frozen=True, slots=True)
class VariantJob:
    source: Path
    base: str  # the source scenario's set name
    variant: str
    work_dir: Path


def run_variant(job: VariantJob) -> dict:
    """One variant of one source fleet through ``csr reconstruct`` (a subprocess, as outside
    evaluators run it) and the contract's metrics; the figures as a plain dict."""
    from csr_core.bench.runner import run_method

    scenario = write_variant(
        job.source, job.work_dir / "scenarios" / job.base / job.variant, VARIANTS[job.variant]
    )
    rec = run_method(scenario, job.work_dir / "runs" / job.base / job.variant, "pipeline")
    row = {
        "base": job.base,
        "variant": job.variant,
        "ok": rec.ok,
        "wall_s": rec.run.wall_s,
        "error": "" if rec.ok else rec.run.stderr_tail[-400:],
    }
    if rec.ok:
        ev = rec.ev.evaluation
        row |= {
            "ate_m": ev.aligned.ate.rmse,
            "rpe_m": ev.aligned.rpe.rmse,
            "mcd_m": ev.map_aligned.mcd,
            "coverage": ev.coverage,
            "km": rec.km,
        }
    return row


def holds(row: dict, original: dict) -> bool:
    """The variant ran, kept every trip the original kept, and stayed within ``HOLD_FACTOR``."""
    return bool(
        row["ok"]
        and original["ok"]
        and row["coverage"] >= original["coverage"]
        and row["ate_m"] <= HOLD_FACTOR * original["ate_m"] + HOLD_SLACK_M
        and row["mcd_m"] <= HOLD_FACTOR * original["mcd_m"] + HOLD_SLACK_M
    )


def run_variants_bench(
    sources: dict[str, Path],
    work_dir: Path,
    names: list[str] | None = None,
    jobs: int = 2,
    progress: Callable[[str], None] | None = None,
) -> list[dict]:
    """Every variant in ``names`` (default all, ``original`` always) of every source fleet."""
    from csr_core.bench.runner import map_in_processes

    chosen = ["original"] + [n for n in (names or list(VARIANTS)) if n != "original"]
    unknown = [n for n in chosen if n not in VARIANTS]
    if unknown:
        raise ValueError(f"unknown variant(s) {unknown}; known: {', '.join(VARIANTS)}")
    work = [VariantJob(src, base, name, work_dir) for base, src in sources.items() for name in chosen]
    return map_in_processes(run_variant, work, jobs, progress, label=lambda r: f"{r['base']} {r['variant']}")


def plot_variants(rows: list[dict], path: Path) -> Path:
    """Aligned ATE of every variant against its fleet's original, one bar group per variant."""
    from csr_core.bench.figures import _plt

    plt = _plt()
    bases = list(dict.fromkeys(r["base"] for r in rows))
    names = list(dict.fromkeys(r["variant"] for r in rows))
    fig, ax = plt.subplots(figsize=(10, 4.2))
    width = 0.8 / max(len(bases), 1)
    for b, base in enumerate(bases):
        by = {r["variant"]: r for r in rows if r["base"] == base}
        ate = [by[n]["ate_m"] if n in by and by[n]["ok"] else np.nan for n in names]
        xs = np.arange(len(names)) + (b - (len(bases) - 1) / 2) * width
        ax.bar(xs, ate, width, label=base)
        o = by.get("original")
        if o and o["ok"]:
            ax.hlines(
                HOLD_FACTOR * o["ate_m"] + HOLD_SLACK_M,
                -0.5,
                len(names) - 0.5,
                colors=f"C{b}",
                linestyles="dashed",
                linewidth=1,
            )
    ax.set_xticks(np.arange(len(names)), names, rotation=35, ha="right")
    ax.set_ylabel("aligned ATE [m]")
    ax.set_title("Foreign fleets through csr reconstruct (dashed: the bound each must hold)")
    ax.legend(fontsize=8)
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def render_section(
    rows: list[dict], elapsed_s: float, regenerate: str, figure: Path | None = None, doc_dir: Path = Path(".")
) -> str:
    """The markdown of BENCHMARKS.md's foreign-fleet section (``figure`` linked relative to
    ``doc_dir``, the folder of the markdown file)."""
    import os
    import time as _time

    from csr_core.bench.tables import duration_text, fmt, markdown_table

    originals = {r["base"]: r for r in rows if r["variant"] == "original"}
    table = []
    for r in rows:
        o = originals[r["base"]]
        if not r["ok"]:
            table.append(
                [
                    r["base"],
                    r["variant"],
                    VARIANTS[r["variant"]].what,
                    "**failed**",
                    "-",
                    "-",
                    "-",
                    "-",
                    "**no**",
                ]
            )
            continue
        ratio = r["ate_m"] / o["ate_m"] if o["ok"] and o["ate_m"] > 0 else float("nan")
        table.append(
            [
                r["base"],
                r["variant"],
                VARIANTS[r["variant"]].what,
                fmt(r["ate_m"]),
                fmt(ratio, 2),
                fmt(r["rpe_m"]),
                fmt(r["mcd_m"]),
                fmt(r["coverage"], 2),
                "yes" if r["variant"] == "original" or holds(r, o) else "**no**",
            ]
        )
    n_hold = sum(1 for r in rows if r["variant"] != "original" and holds(r, originals[r["base"]]))
    n_var = sum(1 for r in rows if r["variant"] != "original")
    return "\n".join(
        [
            "## Foreign fleets (`csr bench-variants`)",
            "",
            f"Regenerate: `{regenerate}` ({duration_text(elapsed_s)} on this machine). Measured "
            f"{_time.strftime('%Y-%m-%d %H:%M UTC', _time.gmtime())}. Each variant rewrites a simulated fleet into "
            "uploads that the contract allows and our simulator never writes (`csr_core/bench/variants.py`; truth "
            "kept consistent), then runs `csr reconstruct` on it as an outside evaluator would and scores it with "
            "the contract's metrics. *holds*: every trip kept, aligned ATE and mCD within "
            f"{HOLD_FACTOR:g}x the original's + {HOLD_SLACK_M:g} m.",
            "",
            f"**{n_hold} of {n_var} variants hold.** Known gaps (variants that show what the pipeline does not do yet): "
            + "; ".join(f"`{v.name}`: {v.gap}" for v in VARIANTS.values() if v.gap)
            + ".",
            "",
            markdown_table(
                [
                    "fleet",
                    "variant",
                    "what changes",
                    "ATE [m]",
                    "x original",
                    "RPE [m]",
                    "mCD [m]",
                    "coverage",
                    "holds",
                ],
                table,
            ),
        ]
        + (
            []
            if figure is None
            else [
                "",
                f"![Foreign fleets: aligned ATE per variant]({Path(os.path.relpath(figure.resolve(), doc_dir.resolve()))})",
            ]
        )
    )
