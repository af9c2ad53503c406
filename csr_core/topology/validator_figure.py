"""A picture of the validator at work on one map: every judged instance coloured by what the
validator said and what it really is (``evaluate.judge_instances``), over the truth."""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

import numpy as np

from csr_core.topology.validation import SUSPECT
from csr_core.types import MapFeature

#: (label, colour, width) by (really wrong, flagged)
KINDS = {
    (True, True): ("wrong, flagged (caught)", "tab:orange", 2.0),
    (True, False): ("wrong, not flagged (missed)", "red", 2.4),
    (False, True): ("right, flagged (false alarm)", "tab:blue", 1.4),
    (False, False): ("right, not flagged", "0.55", 0.8),
}


AUTO_WINDOW_M = 300.0


def _busiest_window(judged: Sequence[tuple[MapFeature, bool, bool]]) -> tuple[float, float, float, float]:
    """The ``AUTO_WINDOW_M`` square around the instance with the most flagged or wrong instances
    within half the window (all instances when none is either)."""
    from scipy.spatial import cKDTree

    mids = np.array([np.asarray(f.points_xy_world, float)[len(f.points_xy_world) // 2] for f, _, _ in judged])
    notable = np.array([bool(w) or bool(set(f.properties.get("flags", ())) & SUSPECT) for f, w, _ in judged])
    pts = mids[notable] if notable.any() else mids
    counts = [len(n) for n in cKDTree(pts).query_ball_point(pts, AUTO_WINDOW_M / 2)]
    cx, cy = pts[int(np.argmax(counts))]
    h = AUTO_WINDOW_M / 2
    return (cx - h, cx + h, cy - h, cy + h)


def plot_validator(
    judged: Sequence[tuple[MapFeature, bool, bool]],
    truth_map: Sequence[MapFeature],
    true_xy: np.ndarray,
    path: str | Path,
    title: str = "",
    bbox_xy: tuple[float, float, float, float] | None = None,
) -> Path:
    """Draw ``judged`` ((instance, really wrong, ...) as ``judge_instances`` returns) over the
    truth (light grey) and the true paths (dotted); legend counts per kind; zoomed to
    ``bbox_xy`` (x0, x1, y0, y1, local metres), else to the ``AUTO_WINDOW_M`` square where the
    validator has most to show (caught, missed and false alarms)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(10, 10))
    for f in truth_map:
        p = np.asarray(f.points_xy_world, float)
        ax.plot(p[:, 0], p[:, 1], color="0.88", lw=3.5, solid_capstyle="round", zorder=1)
    ax.plot(true_xy[::10, 0], true_xy[::10, 1], ",", color="0.7", zorder=1)
    counts = dict.fromkeys(KINDS, 0)
    for f, wrong, _ in judged:
        key = (bool(wrong), bool(set(f.properties.get("flags", ())) & SUSPECT))
        counts[key] += 1
        label, colour, width = KINDS[key]
        p = np.asarray(f.points_xy_world, float)
        closed = f.type.is_polygon and len(p) >= 3
        p = np.vstack([p, p[:1]]) if closed else p
        ax.plot(p[:, 0], p[:, 1], color=colour, lw=width, zorder=3 if wrong or key[1] else 2)
    for key, (label, colour, width) in KINDS.items():
        ax.plot([], [], color=colour, lw=max(width, 2.0), label=f"{label}: {counts[key]}")
    caught = counts[(True, True)]
    n_wrong = caught + counts[(True, False)]
    n_flagged = caught + counts[(False, True)]
    ax.set_title(
        f"{title}  validator recall {caught / max(n_wrong, 1):.2f}, precision {caught / max(n_flagged, 1):.2f}"
    )
    ax.legend(loc="upper right", fontsize=9)
    ax.set_aspect("equal")
    if bbox_xy is None and judged:
        bbox_xy = _busiest_window(judged)
    if bbox_xy is not None:
        ax.set_xlim(bbox_xy[0], bbox_xy[1])
        ax.set_ylim(bbox_xy[2], bbox_xy[3])
    ax.set_xlabel("x [m]")
    ax.set_ylabel("y [m]")
    fig.tight_layout()
    out = Path(path)
    out.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(out, dpi=90)
    plt.close(fig)
    return out
