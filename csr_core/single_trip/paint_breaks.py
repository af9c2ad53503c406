"""Painted lines break at stop lines and crosswalks: a divider's unseen stretch across one is cut.

A dashed divider is spliced across its dash gaps (``SPLICE_MAX_GAP_M``), so one instance spans
the gaps between its dashes, which the map counts as part of the line. Paint also stops at a stop
line and at a crosswalk, and the junction's guide line (or the next road's divider) starts a few
metres on; the splice bridges that break just as it bridges a dash gap, and the bridge lies where
the truth has no line (Karlsruhe, docs/single-trip.md: 3-6 m bridges at most of its
stop lines and crosswalks, in every trip that passes them).

The trip tells the two gaps apart by what lies in them: a stretch of the instance with none of its
own observations within ``gate_m`` that reaches a stop line or crosswalk of the same trip (within
the ``reach_m`` of :func:`barrier_geometry`) is a break in the paint, and the instance is cut there. A stretch
that was observed is never cut: a line painted through a crosswalk stays whole.

Road boundaries and centrelines have no dash gaps: they are continuous where they exist, so
every stretch of one that none of its own observations comes within ``gate_m`` of is cut
(:func:`cut_unseen`), wherever it lies. Such a stretch is a bridge the splice made across a gap
of up to ``SPLICE_MAX_GAP_M`` (most often a centreline round the U-turn the trip made at a dead
end, from one lane's centreline to the other's) or an end carried past what was seen, and on
every simulated world it lies off the truth (docs/single-trip.md).
"""

from __future__ import annotations

import numpy as np
import shapely

from csr_core.single_trip.compiled import search


def barrier_geometry(
    stop_lines_xy: list[np.ndarray], crosswalks_xy: list[np.ndarray], reach_m: float
) -> shapely.Geometry | None:
    """The trip's stop lines and crosswalk outlines widened by ``reach_m``, as one prepared
    geometry (``None`` when the trip has neither)."""
    parts = [shapely.LineString(p) for p in stop_lines_xy if len(p) >= 2]
    parts += [shapely.Polygon(p) for p in crosswalks_xy if len(p) >= 3]
    if not parts:
        return None
    barrier = shapely.union_all([shapely.buffer(g, reach_m) for g in parts])
    shapely.prepare(barrier)
    return barrier


class ObservedPoints:
    """The observed points of one track (world; its detections' polylines concatenated, ``offsets``
    where each starts and the end), asked which vertices of an instance have one within a gate.

    ``step_m``: the polylines count as densified to that spacing (as
    ``observations.track_observations`` densifies them, keeping every point as given). A vertex
    within the gate of a point as given is seen either way, and almost every vertex is
    (Karlsruhe, urban: 99.5 %); only for the rest are the steps densified, and only those with
    an end within the gate plus the step's length. Compiled (``search.seen_within``)."""

    def __init__(
        self, points_w: np.ndarray, offsets: np.ndarray | None = None, step_m: float | None = None
    ) -> None:
        self.points_w = np.ascontiguousarray(points_w, dtype=float)
        self.offsets = np.array([0, len(points_w)]) if offsets is None else offsets
        self.step_m = step_m
        # each point's step to the next point of its polyline (zero after a polyline's last point)
        step = np.zeros_like(self.points_w)
        step[:-1] = self.points_w[1:] - self.points_w[:-1]
        step[self.offsets[1:] - 1] = 0.0
        self._step = step
        self._step_len = np.sqrt(step[:, 0] * step[:, 0] + step[:, 1] * step[:, 1])
        self._sorted: tuple[bool, np.ndarray, np.ndarray] | None = None  # sort_along_wider_axis, once asked

    def seen(self, points_xy: np.ndarray, gate_m: float) -> np.ndarray:
        """``(M,)`` whether each of ``points_xy (M, 2)`` has an observed point within ``gate_m``."""
        if not len(self.points_w) or not len(points_xy):
            return np.zeros(len(points_xy), dtype=bool)
        if self._sorted is None:
            self._sorted = search.sort_along_wider_axis(
                self.points_w[:, 0].copy(), self.points_w[:, 1].copy()
            )
        return search.seen_within(
            np.ascontiguousarray(points_xy, dtype=float),
            self.points_w,
            self._step,
            self._step_len,
            float(self.step_m or 0.0),
            float(gate_m),
            *self._sorted,
        )


def unseen_runs(points_xy: np.ndarray, observed: ObservedPoints, gate_m: float) -> list[tuple[int, int]]:
    """Half-open index ranges ``[a, b)`` of the maximal runs of vertices of ``points_xy`` with no
    observation within ``gate_m``."""
    return _true_runs(~observed.seen(points_xy, gate_m))


def _true_runs(mask: np.ndarray) -> list[tuple[int, int]]:
    edges = np.flatnonzero(np.diff(np.concatenate(([0], mask.astype(np.int8), [0]))))
    return [(int(a), int(b)) for a, b in zip(edges[::2], edges[1::2], strict=True)]


def _without_runs(points_xy: np.ndarray, runs: list[tuple[int, int]]) -> list[np.ndarray]:
    """``points_xy`` split at the vertex ranges ``runs`` (dropped); parts of fewer than two
    vertices are dropped. One part, the input itself, when ``runs`` is empty."""
    if not runs:
        return [points_xy]
    cut = np.zeros(len(points_xy), bool)
    for a, b in runs:
        cut[a:b] = True
    return [points_xy[a:b] for a, b in _true_runs(~cut) if b - a >= 2]


def cut_unseen(points_xy: np.ndarray, observed: ObservedPoints, gate_m: float) -> list[np.ndarray]:
    """``points_xy`` ``(M, 2)`` with its unseen runs (:func:`unseen_runs`) dropped."""
    if len(points_xy) < 2:
        return [points_xy]
    return _without_runs(points_xy, unseen_runs(points_xy, observed, gate_m))


def cut_at_paint_breaks(
    points_xy: np.ndarray, observed: ObservedPoints, barrier: shapely.Geometry | None, gate_m: float
) -> list[np.ndarray]:
    """``points_xy`` ``(M, 2)`` split where an unseen run (:func:`unseen_runs`), together with the
    segments joining it to its seen neighbours, meets ``barrier``; the run itself is dropped."""
    if barrier is None or len(points_xy) < 2:
        return [points_xy]
    n = len(points_xy)  # a run with its seen neighbours always spans at least two vertices here
    return _without_runs(
        points_xy,
        [
            (a, b)
            for a, b in unseen_runs(points_xy, observed, gate_m)
            if barrier.intersects(shapely.LineString(points_xy[max(a - 1, 0) : min(b + 1, n)]))
        ],
    )
