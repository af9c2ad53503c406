"""Benchmark figures (matplotlib, Agg), the kind of pictures in the paper's Figs. 10 and 11.

For one scenario and each method (aligned outputs, contract section 6):

- ``map``: truth (wide grey) against the reconstruction coloured by element type, zoomed;
- ``trajectories``: the estimate raw and after the global alignment over the true trajectories (thin,
  dashed, underneath), zoomed;
- ``heatmap``: every kept truth sample coloured by its capped distance to the reconstruction.
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np
from scipy.spatial import cKDTree

from csr_core.bench.evaluate import SAME_ROAD_RADIUS_M
from csr_core.bench.runner import Record
from csr_core.bench.tables import METHOD_NAMES
from csr_core.metrics import CD_CAP_M, apply_se2, transform_features
from csr_core.types import ElementType, MapFeature

TYPE_COLOURS = {
    ElementType.LANE_DIVIDER: "tab:blue",
    ElementType.CENTERLINE: "tab:green",
    ElementType.ROAD_BOUNDARY: "tab:red",
    ElementType.STOP_LINE: "tab:purple",
    ElementType.CROSSWALK: "tab:orange",
    ElementType.ROAD_MARKING: "tab:brown",
}


def _plt():
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def _chain(f: MapFeature) -> np.ndarray:
    p = f.points_xy_world
    return np.vstack([p, p[:1]]) if f.type.is_polygon and len(p) > 2 else p


def zoom_centre(record: Record) -> np.ndarray:
    """A window centre where many trips pass and many element types meet: the true stop line or
    crosswalk seen by the most trips (a trip frame within 10 m), else the true trajectory frame
    with the most trips nearby."""
    ev = record.ev
    trees = [cKDTree(xy) for xy in ev.true_xy_by_key.values()]

    def n_trips(point: np.ndarray) -> int:
        return sum(1 for t in trees if np.isfinite(t.query(point, distance_upper_bound=10.0)[0]))

    candidates = [
        f.points_xy_world.mean(axis=0)
        for f in ev.truth_map
        if f.type in (ElementType.STOP_LINE, ElementType.CROSSWALK)
    ]
    if not candidates:
        frames = np.concatenate(list(ev.true_xy_by_key.values()))
        candidates = list(frames[:: max(1, len(frames) // 400)])
    counts = [n_trips(c) for c in candidates]
    return np.asarray(candidates[int(np.argmax(counts))])


def _window(ax, centre: np.ndarray, half_w: float, half_h: float) -> None:
    ax.set_xlim(centre[0] - half_w, centre[0] + half_w)
    ax.set_ylim(centre[1] - half_h, centre[1] + half_h)
    ax.set_aspect("equal")
    ax.tick_params(labelsize=7)


def _panels(n: int, width_in: float = 5.2, height_in: float = 4.2):
    plt = _plt()
    fig, axes = plt.subplots(1, n, figsize=(width_in * n, height_in), squeeze=False)
    return plt, fig, axes[0]


def plot_map(records: Sequence[Record], path: Path, half_w: float = 30.0, half_h: float = 18.0) -> Path:
    ok = [r for r in records if r.ok]
    plt, fig, axes = _panels(len(ok))
    centre = zoom_centre(ok[0])
    for ax, r in zip(axes, ok, strict=False):
        ev = r.ev
        pred = transform_features(ev.evaluation.truth_T_est, ev.pred_map)
        for f in ev.truth_map:
            c = _chain(f)
            ax.plot(c[:, 0], c[:, 1], color="0.75", lw=4.0, solid_capstyle="round", zorder=1)
        for f in pred:
            c = _chain(f)
            ax.plot(c[:, 0], c[:, 1], color=TYPE_COLOURS[f.type], lw=0.7, alpha=0.85, zorder=2)
        _window(ax, centre, half_w, half_h)
        ax.set_title(
            f"{METHOD_NAMES.get(r.method, r.method)}  mCD {ev.evaluation.map_aligned.mcd:.3f} m", fontsize=9
        )
    handles = [plt.Line2D([], [], color="0.75", lw=4, label="truth")]
    handles += [plt.Line2D([], [], color=c, lw=1.5, label=t.value) for t, c in TYPE_COLOURS.items()]
    fig.legend(handles=handles, loc="lower center", ncol=len(handles), fontsize=8, frameon=False)
    fig.suptitle(
        f"{ok[0].scenario}: truth vs reconstruction (aligned), {2 * half_w:.0f} m x {2 * half_h:.0f} m",
        fontsize=10,
    )
    fig.tight_layout(rect=(0, 0.06, 1, 0.95))
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


#: the trajectory figure's styles: the truth thin, dashed and underneath, the estimates drawn over it
#: (the aligned one on top), so that an estimate on the truth stays visible
TRUTH_STYLE: dict[str, Any] = {"color": "k", "lw": 0.8, "ls": (0, (4, 3)), "zorder": 1}
RAW_STYLE: dict[str, Any] = {"color": "tab:red", "lw": 0.9, "ls": "-", "zorder": 2}
ALIGNED_STYLE: dict[str, Any] = {"color": "tab:blue", "lw": 1.3, "ls": "-", "zorder": 3}


def draw_trajectories(
    ax,
    true_xy_by_key: dict[str, np.ndarray],
    est_xy_by_key: dict[str, np.ndarray],
    truth_T_est: np.ndarray,
) -> dict[str, list]:
    """Each trip's true trajectory ``(N, 2)`` and its estimate ``(M, 2)``, raw and moved by
    ``truth_T_est`` ``(3,)``, on ``ax``; returns the lines drawn by role (``truth``, ``raw``,
    ``aligned``)."""
    lines: dict[str, list] = {"truth": [], "raw": [], "aligned": []}
    for k, true_xy in true_xy_by_key.items():
        lines["truth"] += ax.plot(true_xy[:, 0], true_xy[:, 1], **TRUTH_STYLE)
        if k in est_xy_by_key:
            est = est_xy_by_key[k]
            lines["raw"] += ax.plot(est[:, 0], est[:, 1], **RAW_STYLE)
            aligned = apply_se2(truth_T_est, est)
            lines["aligned"] += ax.plot(aligned[:, 0], aligned[:, 1], **ALIGNED_STYLE)
    return lines


def plot_trajectories(
    records: Sequence[Record], path: Path, half_w: float = 15.0, half_h: float = 9.0
) -> Path:
    ok = [r for r in records if r.ok]
    plt, fig, axes = _panels(len(ok))
    centre = zoom_centre(ok[0])
    for ax, r in zip(axes, ok, strict=False):
        ev = r.ev
        draw_trajectories(ax, ev.true_xy_by_key, ev.est_xy_by_key, ev.evaluation.truth_T_est)
        _window(ax, centre, half_w, half_h)
        e = ev.evaluation
        ax.set_title(
            f"{METHOD_NAMES.get(r.method, r.method)}\nATE raw {e.raw.ate.rmse:.2f} m, aligned "
            f"{e.aligned.ate.rmse:.2f} m; RPE {e.aligned.rpe.rmse:.3f} m",
            fontsize=8,
        )
    legend_style = {
        "truth": TRUTH_STYLE,
        "estimate, raw": RAW_STYLE,
        "estimate, globally aligned": ALIGNED_STYLE,
    }
    handles = [
        plt.Line2D([], [], color=st["color"], lw=max(st["lw"], 1.0), ls=st["ls"], label=label)
        for label, st in legend_style.items()
    ]
    fig.legend(handles=handles, loc="lower center", ncol=3, fontsize=8, frameon=False)
    fig.suptitle(
        f"{ok[0].scenario}: trajectories before and after the global alignment "
        f"({2 * half_w:.0f} m x {2 * half_h:.0f} m)",
        fontsize=10,
    )
    fig.tight_layout(rect=(0, 0.06, 1, 0.93))
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def plot_error_heatmap(records: Sequence[Record], path: Path) -> Path:
    ok = [r for r in records if r.ok]
    plt, fig, axes = _panels(len(ok), 5.2, 4.6)
    sc = None
    for ax, r in zip(axes, ok, strict=False):
        m = r.ev.evaluation.map_aligned
        xy = np.concatenate([m.truth_samples_xy[t] for t in m.truth_samples_xy if len(m.truth_samples_xy[t])])
        err = np.concatenate(
            [m.truth_sample_error_m[t] for t in m.truth_samples_xy if len(m.truth_samples_xy[t])]
        )
        order = np.argsort(err)
        sc = ax.scatter(
            xy[order, 0],
            xy[order, 1],
            c=err[order],
            s=0.6,
            cmap="inferno_r",
            vmin=0.0,
            vmax=CD_CAP_M / 2,
            linewidths=0,
        )
        ax.set_aspect("equal")
        ax.tick_params(labelsize=7)
        ax.set_title(f"{METHOD_NAMES.get(r.method, r.method)}  mCD {m.mcd:.3f} m", fontsize=9)
    cbar = fig.colorbar(sc, ax=list(axes), shrink=0.8, pad=0.01)
    cbar.set_label(
        "truth sample -> reconstruction distance [m] (capped 1 m; colour scale to 0.5 m)", fontsize=8
    )
    fig.suptitle(f"{ok[0].scenario}: map error along the truth (aligned)", fontsize=10)
    fig.savefig(path, dpi=110, bbox_inches="tight")
    plt.close(fig)
    return path


def make_figures(records: Sequence[Record], out_dir: Path, stem: str) -> list[tuple[str, Path]]:
    """All three figures for one scenario's records (one per method); ``(caption, path)`` list."""
    out_dir.mkdir(parents=True, exist_ok=True)
    return [
        (
            "Truth vs reconstruction per element type (aligned, zoomed)",
            plot_map(records, out_dir / f"{stem}_map.png"),
        ),
        (
            "Trajectories before and after the global alignment (zoomed)",
            plot_trajectories(records, out_dir / f"{stem}_trajectories.png"),
        ),
        (
            "Map error heat map (distance from each truth sample to the reconstruction)",
            plot_error_heatmap(records, out_dir / f"{stem}_error_heatmap.png"),
        ),
    ]


#: the aligned ATE target, drawn on the density figure
ATE_TARGET_M = 0.10


def plot_ate_by_density(records: Sequence[Record], path: Path) -> Path | None:
    """Aligned ATE of every scenario of the set against how many trips drive each of its places
    (``trips_per_place``), one marker per method: the figure to read the targets' ">= 10 trips per
    road" target against. None when fewer than two scenarios were scored."""
    main = [r for r in records if r.ok and not r.variant]
    if len({r.scenario for r in main}) < 2:
        return None
    path.parent.mkdir(parents=True, exist_ok=True)
    plt = _plt()
    fig, ax = plt.subplots(figsize=(6.4, 4.2))
    markers = {"pipeline": "o", "gnss_only": "x", "roadmap_icp": "^"}
    for method in dict.fromkeys(r.method for r in main):
        rs = [r for r in main if r.method == method]
        x = [r.ev.trips_per_place for r in rs]
        y = [r.ev.evaluation.aligned.ate.rmse for r in rs]
        ax.scatter(x, y, marker=markers.get(method, "s"), label=METHOD_NAMES.get(method, method), s=28)
        if method == "pipeline":
            for r, xi, yi in zip(rs, x, y, strict=True):
                ax.annotate(
                    f"{r.world} {r.scenario.rsplit('-', 1)[-1]}",
                    (xi, yi),
                    fontsize=6,
                    xytext=(3, 2),
                    textcoords="offset points",
                )
    ax.axhline(ATE_TARGET_M, color="grey", lw=0.8, ls="--")
    ax.text(ax.get_xlim()[0], ATE_TARGET_M, " target", fontsize=7, va="bottom", color="grey")
    ax.set_yscale("log")
    ax.set_xlabel(
        f"trips per place (median over frames: trips whose true path passes within {SAME_ROAD_RADIUS_M:g} m)"
    )
    ax.set_ylabel("aligned ATE RMSE [m]")
    ax.legend(fontsize=7)
    ax.set_title("Pose error against fleet density, one point per scenario", fontsize=10)
    fig.savefig(path, dpi=110, bbox_inches="tight")
    plt.close(fig)
    return path
