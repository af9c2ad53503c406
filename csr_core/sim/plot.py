"""A picture of a world's truth map and some true trajectories (PNG, matplotlib Agg)."""

from __future__ import annotations

import logging
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from csr_core.sim.world import World
from csr_core.types import DividerStyle, ElementType

log = logging.getLogger(__name__)

_STYLE: dict[ElementType, dict[str, Any]] = {
    ElementType.ROAD_BOUNDARY: dict(color="black", lw=0.9),
    ElementType.LANE_DIVIDER: dict(color="tab:orange", lw=0.6),
    ElementType.CENTERLINE: dict(color="tab:blue", lw=0.35, alpha=0.5),
    ElementType.STOP_LINE: dict(color="red", lw=1.5),
    ElementType.CROSSWALK: dict(color="tab:green", lw=0.8),
}


def plot_world(
    world: World,
    out_png: str | Path,
    trajectories_xy: Sequence[np.ndarray] = (),
    bbox_xy: tuple[float, float, float, float] | None = None,
    show_lane_graph: bool = False,
) -> Path:
    """Draw the truth map (world frame, metres), optional ``trajectories_xy`` ``(N, 2)`` arrays and
    hidden lane-graph connectors; ``bbox_xy = (xmin, ymin, xmax, ymax)`` zooms in."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(12, 10), dpi=110)
    for e in world.elements:
        style: dict[str, Any] = dict(_STYLE.get(e.type, dict(color="gray", lw=0.5)))
        pts = e.points_xy_world
        if e.type.is_polygon:
            pts = np.vstack([pts, pts[:1]])
        if e.type == ElementType.LANE_DIVIDER and e.style == DividerStyle.DASHED:
            style["ls"] = (0, (3, 3))
        if e.type == ElementType.LANE_DIVIDER and e.style == DividerStyle.DOUBLE:
            style["lw"] = 1.4
        ax.plot(pts[:, 0], pts[:, 1], **style)
    if show_lane_graph:
        for _, data in world.lane_graph.nodes(data=True):
            if not data["visible"]:
                c = data["centerline_xy"]
                ax.plot(c[:, 0], c[:, 1], color="gray", lw=0.5, ls=":")
    colors = plt.cm.tab10(np.linspace(0, 1, 10))
    for k, traj in enumerate(trajectories_xy):
        ax.plot(traj[:, 0], traj[:, 1], color=colors[k % 10], lw=1.2, alpha=0.8)
        ax.plot(traj[:1, 0], traj[:1, 1], "o", color=colors[k % 10], ms=4)
    for x, y, r in world.canyon_zones_xyr:
        ax.add_patch(plt.Circle((x, y), r, color="purple", alpha=0.08))
    if bbox_xy is not None:
        ax.set_xlim(bbox_xy[0], bbox_xy[2])
        ax.set_ylim(bbox_xy[1], bbox_xy[3])
    ax.set_aspect("equal")
    ax.set_title(f"{world.name}: truth map ({len(world.elements)} elements), {len(trajectories_xy)} trips")
    ax.set_xlabel("x east [m]")
    ax.set_ylabel("y north [m]")
    out_png = Path(out_png)
    out_png.parent.mkdir(parents=True, exist_ok=True)
    fig.tight_layout()
    fig.savefig(out_png)
    plt.close(fig)
    log.info("wrote %s", out_png)
    return out_png
