"""How the viewer shows each validator flag kind (TileJSON ``flag_levels``).

- ``severe``: a suspect flag saying the evidence contradicts itself (``trips_disagree``,
  ``implausible_lane_width``, ``high_variance``, ``high_residual_pair``): the flags that hold a merge
  back for review; on the validator benchmark two thirds of ``implausible_lane_width`` instances
  were really wrong.
- ``warning``: suspect, but nothing contradicts: ``low_support`` (few trips saw it yet; a quarter of
  such instances were really wrong on the same benchmark), ``degraded_support`` (trips whose poses
  failed their integrity test support it) and ``seam_gap`` (its end misses the neighbour tile's).
- ``info``: severity 0 in the tile score (``gap``, ``outlier_trip``, ``low_support_marking``).

A kind not listed here is shown as ``info``.
"""

from __future__ import annotations

from enum import StrEnum

from csr_core.topology.degraded import DEGRADED_SUPPORT
from csr_core.topology.validation import SEVERITY, SUSPECT

SEAM_GAP = "seam_gap"  # set by the merge job (workers.tile_jobs) at tile seams


class FlagLevel(StrEnum):
    SEVERE = "severe"
    WARNING = "warning"
    INFO = "info"


WARNING_FLAGS = frozenset({"low_support", DEGRADED_SUPPORT, SEAM_GAP})


def flag_levels() -> dict[str, FlagLevel]:
    """Every flag kind the pipeline sets, with its level (module docstring)."""
    kinds = sorted({*SEVERITY, DEGRADED_SUPPORT, SEAM_GAP})
    return {
        kind: (
            FlagLevel.WARNING
            if kind in WARNING_FLAGS
            else FlagLevel.SEVERE
            if kind in SUSPECT
            else FlagLevel.INFO
        )
        for kind in kinds
    }
