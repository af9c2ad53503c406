"""Compare the GNSS model with a real consumer receiver: the comma2k19 u-blox log against the
fused reference pose (comma2k19 segment 40, 60 s on the I-280; the arrays it reads ship in
``csr_core/sim/data/comma2k19``, MIT).

Both the real fix and the model are scored the same way against the same reference track:
horizontal error median / p95, and its along-track / cross-track components (relative to the
reference velocity), plus the latency that best explains the along-track error.
The model is run many times (seeds) on the reference trajectory with the ``single`` status of
the chosen profile, so its figures come with a spread.

    python -m csr_core.sim.gnss_calibration [--profile standard] [--runs 200] [--out docs/gnss-model.md]
"""

from __future__ import annotations

import argparse
import dataclasses
import logging
import os
from pathlib import Path

import numpy as np
import pyproj

from csr_core.geo import LocalFrame
from csr_core.sim.gnss import draw_receiver, simulate_gnss
from csr_core.sim.profiles import GnssParams, get_profile

log = logging.getLogger(__name__)

DEFAULT_SEGMENT = Path(__file__).resolve().parent / "data" / "comma2k19" / "segment_40"
SEGMENT_ENV = "CSR_COMMA2K19_SEGMENT"
LAG_GRID_S = np.arange(0.0, 0.2001, 0.001)
SINGLE = 3


@dataclasses.dataclass(frozen=True)
class Reference:
    """The fused pose track in a local frame, and the u-blox fixes."""

    t_s: np.ndarray  # (N,) reference times
    xy_m: np.ndarray  # (N, 2)
    fix_t_s: np.ndarray  # (K,) u-blox times
    fix_xy_m: np.ndarray  # (K, 2)


def segment_dir() -> Path:
    return Path(os.environ.get(SEGMENT_ENV, DEFAULT_SEGMENT))


def load_reference(folder: Path | None = None) -> Reference:
    folder = folder or segment_dir()
    ecef = np.load(folder / "global_pose" / "frame_positions")
    t = np.load(folder / "global_pose" / "frame_times")
    ublox = np.load(folder / "processed_log" / "GNSS" / "live_gnss_ublox" / "value")
    ublox_t = np.load(folder / "processed_log" / "GNSS" / "live_gnss_ublox" / "t")
    to_lla = pyproj.Transformer.from_crs("EPSG:4978", "EPSG:4979", always_xy=True)
    lon, lat, _ = to_lla.transform(ecef[:, 0], ecef[:, 1], ecef[:, 2])
    frame = LocalFrame(float(np.mean(lat)), float(np.mean(lon)))
    xy = frame.to_local(np.column_stack([lon, lat]))
    fix_xy = frame.to_local(ublox[:, [1, 0]])
    inside = (ublox_t >= t[0]) & (ublox_t <= t[-1])
    return Reference(t, xy, ublox_t[inside], fix_xy[inside])


def error_stats(
    t_s: np.ndarray, xy_m: np.ndarray, fix_t_s: np.ndarray, fix_xy_m: np.ndarray
) -> dict[str, float]:
    """Error figures of fixes against a reference track (interpolated at the fix times)."""
    ref = np.column_stack([np.interp(fix_t_s, t_s, xy_m[:, k]) for k in range(2)])
    vel = np.column_stack([np.interp(fix_t_s, t_s, np.gradient(xy_m[:, k], t_s)) for k in range(2)])
    speed = np.linalg.norm(vel, axis=1)
    along_dir = vel / np.maximum(speed, 1e-6)[:, None]
    err = fix_xy_m - ref
    along = np.sum(err * along_dir, axis=1)
    cross = along_dir[:, 0] * err[:, 1] - along_dir[:, 1] * err[:, 0]
    horiz = np.linalg.norm(err, axis=1)
    # latency: the lag whose lagged reference best explains the fixes (least squares over a grid)
    costs = []
    for lag in LAG_GRID_S:
        lagged = np.column_stack([np.interp(fix_t_s - lag, t_s, xy_m[:, k]) for k in range(2)])
        costs.append(np.mean(np.sum((fix_xy_m - lagged) ** 2, axis=1)))
    best_lag = float(LAG_GRID_S[int(np.argmin(costs))])
    along_resid = along + speed * best_lag
    return {
        "median_m": float(np.median(horiz)),
        "p95_m": float(np.percentile(horiz, 95)),
        "along_mean_m": float(np.mean(along)),
        "along_std_m": float(np.std(along)),
        "cross_mean_m": float(np.mean(cross)),
        "cross_std_m": float(np.std(cross)),
        "latency_s": best_lag,
        "along_std_after_latency_m": float(np.std(along_resid)),
        "speed_mps": float(np.mean(speed)),
    }


def model_stats(
    ref: Reference, params: GnssParams, n_runs: int, seed: int = 0
) -> dict[str, dict[str, float]]:
    """Figures of the model's ``single`` status on the reference track: median and 5-95 % over runs."""
    single_only = dataclasses.replace(
        params,
        initial_probs=(0.0, 0.0, 0.0, 1.0),
        transition_probs=tuple((0.0,) * 4 for _ in range(4)),
    )
    t0 = max(ref.t_s[0], ref.fix_t_s[0])
    t = np.arange(t0, ref.t_s[-1], 1.0 / single_only.rate_hz)
    xy = np.column_stack([np.interp(t, ref.t_s, ref.xy_m[:, k]) for k in range(2)])
    vel = np.gradient(xy, t, axis=0)
    poses = np.column_stack([xy, np.arctan2(vel[:, 1], vel[:, 0])])
    speed = np.linalg.norm(vel, axis=1)
    runs = []
    for k in range(n_runs):
        rng = np.random.default_rng([seed, k])
        receiver = draw_receiver(
            dataclasses.replace(single_only, rtk_receiver_share=0.0), rng
        )  # a consumer one
        g = simulate_gnss(t - t0, poses, speed, single_only, np.zeros((0, 3)), rng, receiver)
        runs.append(error_stats(ref.t_s, ref.xy_m, t, g.position_xy_world))
    keys = runs[0].keys()
    return {
        key: {
            "median": float(np.median([r[key] for r in runs])),
            "p05": float(np.percentile([r[key] for r in runs], 5)),
            "p95": float(np.percentile([r[key] for r in runs], 95)),
            # magnitudes for signed figures (bias sign is random in the model)
            "abs_median": float(np.median([abs(r[key]) for r in runs])),
        }
        for key in keys
    }


_ROWS = (
    ("median_m", "horizontal error, median [m]"),
    ("p95_m", "horizontal error, p95 [m]"),
    ("along_mean_m", "along-track error, mean [m] (negative: behind)"),
    ("along_std_m", "along-track error, std [m]"),
    ("cross_mean_m", "cross-track error, mean [m]"),
    ("cross_std_m", "cross-track error, std [m]"),
    ("latency_s", "best-fit latency [s]"),
    ("along_std_after_latency_m", "along-track std after removing latency [m]"),
)


def report_markdown(profile_name: str = "standard", n_runs: int = 200) -> str:
    ref = load_reference()
    real = error_stats(ref.t_s, ref.xy_m, ref.fix_t_s, ref.fix_xy_m)
    params = get_profile(profile_name).gnss
    model = model_stats(ref, params, n_runs)
    single = params.status_models[SINGLE]
    lines = [
        "# GNSS model vs. the real u-blox (comma2k19)",
        "",
        "Generated by `python -m csr_core.sim.gnss_calibration --profile "
        f"{profile_name} --runs {n_runs} --out docs/gnss-model.md` (`csr_core/sim/gnss_calibration.py`).",
        "",
        f"Reference: comma2k19 segment 40, {ref.t_s[-1] - ref.t_s[0]:.0f} s, {len(ref.fix_t_s)} u-blox fixes at 10 Hz, "
        f"mean speed {real['speed_mps']:.1f} m/s (I-280). Truth = the fused `global_pose` track; "
        "errors are the fix minus the reference interpolated at the fix time, split along / across "
        "the reference velocity.",
        "",
        f"Model (`{profile_name}` profile, consumer receiver, status `single`): latency {params.latency_mean_s:.3f} s "
        f"(sigma between vehicles {params.latency_sigma_s:.3f} s, per-fix jitter {params.latency_jitter_s:.3f} s), "
        f"Gauss-Markov bias sigma {single.bias_sigma_m:.2f} m per axis "
        f"with tau {single.bias_tau_s:.0f} s, white noise {single.white_sigma_m:.2f} m per axis; "
        f"run {n_runs} times on the same reference trajectory (median and 5-95 % range over runs).",
        "",
        "| figure | real u-blox | model median | model 5-95 % over runs |",
        "| --- | ---: | ---: | ---: |",
    ]
    for key, label in _ROWS:
        m = model[key]
        lines.append(f"| {label} | {real[key]:.3f} | {m['median']:.3f} | {m['p05']:.3f} .. {m['p95']:.3f} |")
    lines += [
        "",
        "## Reading",
        "",
        f"- The real fix lags: {real['latency_s'] * 1000:.0f} ms best-fit latency, i.e. "
        f"{-real['along_mean_m']:.2f} m behind at {real['speed_mps']:.1f} m/s. The model reproduces it with its "
        f"latency term (median along-track mean {model['along_mean_m']['median']:.2f} m); this error grows with speed "
        f"(about {13.9 * params.latency_mean_s:.1f} m at 50 km/h, {33.3 * params.latency_mean_s:.1f} m at 120 km/h) "
        "and is not part of the reported `std_m`, as with real receivers. The per-fix time-tag jitter explains "
        "why the real along-track spread (after removing the lag) is larger than the cross-track one.",
        f"- Real cross-track: a near-constant offset {real['cross_mean_m']:.2f} m with {real['cross_std_m']:.2f} m spread over "
        f"the minute; the model's slowly varying bias gives offsets of typical size "
        f"{model['cross_mean_m']['abs_median']:.2f} m (median |mean| over runs) with spread "
        f"{model['cross_std_m']['median']:.2f} m in a minute.",
        f"- Median horizontal error: real {real['median_m']:.2f} m, model {model['median_m']['median']:.2f} m "
        f"(5-95 %: {model['median_m']['p05']:.2f} .. {model['median_m']['p95']:.2f}); "
        f"p95: real {real['p95_m']:.2f} m, model {model['p95_m']['median']:.2f} m.",
        "- One minute of one receiver cannot pin down the bias time constant or its long-run size: "
        f"tau = {single.bias_tau_s:.0f} s and sigma = {single.bias_sigma_m:.2f} m are assumptions consistent with the "
        "log (bias nearly constant over 60 s, size a few decimetres) and with typical SBAS-aided single-point "
        "fixes; the model's runs cover the real figures within their spread.",
        f"- In a simulated fleet the latency applies to consumer receivers ({1 - params.rtk_receiver_share:.0%} of the "
        f"vehicles in `{profile_name}`); RTK-capable receivers time-tag their fixes at the epoch (no lag).",
        "- Not modelled from this log: the phone chip (`live_gnss_qcom`, 0.5 Hz, median 2.5 m) and multipath "
        "in cities (the `hard` profile's canyon jumps and outages are assumptions, not measured here).",
        "",
    ]
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--profile", default="standard")
    parser.add_argument("--runs", type=int, default=200)
    parser.add_argument("--out", default="docs/gnss-model.md")
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.INFO)
    text = report_markdown(args.profile, args.runs)
    Path(args.out).write_text(text)
    log.info("wrote %s", args.out)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
