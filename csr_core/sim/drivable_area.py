"""Road boundaries derived from lanelets where a map does not draw them: the outline of the
drivable area.

The drivable area is the union of the lanelet polygons (each the ring left bound, reversed right
bound), closed over gaps narrower than ``CLOSE_GAP_M``. Its outline (outer rings and the rings of
holes such as city blocks) is the road boundary, less the pieces that are not kerbs:

- the caps where the mapped network is cut off (the start of a lanelet without predecessor, the
  end of one without successor), within ``CAP_TOLERANCE_M``;
- pieces along lines the caller names (``exclude_lines``, e.g. painted edge lines that a map uses
  as the bound while the kerb beyond them is not mapped), within ``CAP_TOLERANCE_M``;
- pieces shorter than ``MIN_PIECE_M``.

Everything is in the world frame (x east, y north, metres); outlines come back as ``(M, 2)``
polylines in the ring's own orientation (shapely's: exterior counter-clockwise).
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
import shapely
from shapely.geometry import LineString, MultiLineString, Polygon
from shapely.ops import unary_union

CLOSE_GAP_M = 0.05
CAP_TOLERANCE_M = 0.3
MIN_PIECE_M = 1.0


def lanelet_polygon(left_xy: np.ndarray, right_xy: np.ndarray) -> Polygon:
    """The area between two bounds ``(M, 2)`` oriented alike (both in the direction of travel)."""
    ring = np.vstack([left_xy, right_xy[::-1]])
    return shapely.make_valid(Polygon(ring)) if len(ring) >= 3 else Polygon()


def outline_boundaries(
    polygons: Sequence[Polygon],
    caps_xy: Sequence[np.ndarray],
    exclude_lines_xy: Sequence[np.ndarray] = (),
) -> list[np.ndarray]:
    """Road boundaries ``[(M, 2)]``: the drivable area's outline less ``caps_xy`` (segments
    ``(2, 2)`` across the cut-off ends of the network) and ``exclude_lines_xy``."""
    area = unary_union([p.buffer(CLOSE_GAP_M) for p in polygons if not p.is_empty]).buffer(-CLOSE_GAP_M)
    rings: list[LineString] = []
    for part in getattr(area, "geoms", [area]):
        if isinstance(part, Polygon) and not part.is_empty:
            rings.append(LineString(part.exterior.coords))
            rings.extend(LineString(r.coords) for r in part.interiors)
    cut = [LineString(c) for c in caps_xy if len(c) >= 2] + [
        LineString(line) for line in exclude_lines_xy if len(line) >= 2
    ]
    mask = unary_union([c.buffer(CAP_TOLERANCE_M) for c in cut]) if cut else None
    out: list[np.ndarray] = []
    for ring in rings:
        kept = ring.difference(mask) if mask is not None else ring
        kept = shapely.line_merge(kept) if isinstance(kept, MultiLineString) else kept
        for piece in getattr(kept, "geoms", [kept]):
            if isinstance(piece, LineString) and piece.length >= MIN_PIECE_M:
                out.append(np.asarray(piece.coords, float)[:, :2])
    return out
