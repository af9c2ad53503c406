"""Human corrections of the data association (paper III-E, "human correction", after the
interactive SLAM of ref. [30]): a pair the map team rejects leaves D*, a pair it adds joins D* as
a known inlier with a large weight, before the pose graph (Eq. 9) is solved again.

Pairs are named by trips and frame ranges, not by sub-map ids, so that a correction still applies
when the sub-maps are split again: a rejected pair removes every accepted pair between a sub-map
of trip ``i`` overlapping ``frames_i`` and one of trip ``j`` overlapping ``frames_j`` (either
order); an added pair registers the two sub-maps of one circle that best cover the frames (a
later rejection of the same frames wins over it).
``PRIOR_KEY`` names the pre-built map (its frames are ignored).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, replace

import numpy as np

from csr_core.alignment.association import PairMatch, match_pair
from csr_core.alignment.params import AlignmentParams, NoiseScales
from csr_core.alignment.submaps import Circle, Submap

PRIOR_KEY = "<prior>"
HUMAN_SIGMA_XY_M = 0.02  # the weight of an added pair: 2 cm, 0.1 degree
HUMAN_SIGMA_YAW_RAD = 0.002


@dataclass(frozen=True, slots=True)
class PairConstraint:
    """A pair of sub-maps named by trip keys and frame ranges (inclusive). ``offset_xyyaw``
    (added pairs only): the pose of ``j``'s data in ``i``'s, in the circle's local frame, as the
    human asserts it; ``None`` registers the two sub-maps (graph matching + GNC) instead."""

    trip_key_i: str
    frames_i: tuple[int, int]
    trip_key_j: str
    frames_j: tuple[int, int]
    offset_xyyaw: tuple[float, float, float] | None = None


@dataclass(frozen=True, slots=True)
class MatchCorrections:
    rejected: tuple[PairConstraint, ...] = ()
    added: tuple[PairConstraint, ...] = ()

    def __bool__(self) -> bool:
        return bool(self.rejected or self.added)


def _covers(s: Submap, key: str, frames: tuple[int, int]) -> bool:
    if key == PRIOR_KEY:
        return s.is_prior
    return not s.is_prior and s.trip_key == key and s.first_frame <= frames[1] and s.last_frame >= frames[0]


def _names(m: PairMatch, submaps: Sequence[Submap], c: PairConstraint) -> bool:
    si, sj = submaps[m.i], submaps[m.j]
    return (_covers(si, c.trip_key_i, c.frames_i) and _covers(sj, c.trip_key_j, c.frames_j)) or (
        _covers(si, c.trip_key_j, c.frames_j) and _covers(sj, c.trip_key_i, c.frames_i)
    )


def _overlap(s: Submap, frames: tuple[int, int]) -> int:
    return 1 if s.is_prior else max(0, min(s.last_frame, frames[1]) - max(s.first_frame, frames[0]) + 1)


def human_pair(
    si: Submap,
    sj: Submap,
    circle: Circle,
    noise: NoiseScales,
    params: AlignmentParams,
    offset_xyyaw: tuple[float, float, float] | None,
) -> PairMatch | None:
    """An added pair: registered, or as asserted; a known inlier with the human weight."""
    if offset_xyyaw is None:
        m = match_pair(si, sj, circle, noise, params)
        if m is None:
            return None
    else:
        m = PairMatch(
            si.submap_id,
            sj.submap_id,
            si.trip_index,
            sj.trip_index,
            circle.circle_id,
            circle.centre_xy_world.copy(),
            np.asarray(offset_xyyaw, float),
            np.eye(3),
            (),
            (),
            np.ones(0),
            1.0,
            0.0,
            float("nan"),
        )
    info = np.diag([HUMAN_SIGMA_XY_M**-2, HUMAN_SIGMA_XY_M**-2, HUMAN_SIGMA_YAW_RAD**-2])
    return replace(m, information_local=info / params.reg_alpha, confidence=1.0, human=True)


def apply_corrections(
    matches: Sequence[PairMatch],
    submaps: Sequence[Submap],
    circles: Sequence[Circle],
    noise: NoiseScales,
    params: AlignmentParams,
    corrections: MatchCorrections,
) -> list[PairMatch]:
    """D* after the human corrections: rejected pairs out, added pairs in."""
    kept = [m for m in matches if not any(_names(m, submaps, c) for c in corrections.rejected)]
    for c in corrections.added:
        best = None
        for si in submaps:
            if not _covers(si, c.trip_key_i, c.frames_i):
                continue
            for sj in submaps:
                if (
                    sj.circle_id != si.circle_id
                    or sj.submap_id == si.submap_id
                    or not _covers(sj, c.trip_key_j, c.frames_j)
                ):
                    continue
                score = _overlap(si, c.frames_i) + _overlap(sj, c.frames_j)
                if best is None or score > best[0]:
                    best = (score, si, sj)
        if best is None:
            continue  # the named frames share no circle: nothing to add (reported by the caller)
        _, si, sj = best
        m = human_pair(si, sj, circles[si.circle_id], noise, params, c.offset_xyyaw)
        if m is not None and not any(_names(m, submaps, r) for r in corrections.rejected):
            kept = [k for k in kept if {k.i, k.j} != {m.i, m.j}] + [m]
    return kept
