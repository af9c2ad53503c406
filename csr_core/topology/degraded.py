"""Map features of degraded trips: flagged, and held back when only such trips support them.

A trip is degraded when its poses failed the integrity test against its own GNSS even after
the repair (``single_trip.integrity``): its GNSS-anchored poses are as good as its fixes and
no better, so the elements it saw may sit metres off. A feature it supports carries the flag
``degraded_support`` and the number of such trips (``degraded_trips``); a feature only degraded
trips support is held back, like a ghost, for a person to look at, and published once trips
that passed confirm it.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import replace

from csr_core.types import MapFeature

DEGRADED_SUPPORT = "degraded_support"


def hold_back_degraded(
    features: Sequence[MapFeature], held_back: Sequence[MapFeature], degraded: set[str]
) -> tuple[tuple[MapFeature, ...], tuple[MapFeature, ...]]:
    """``(published, held back)``: ``features`` of the trips in ``degraded`` flagged, those only
    they support moved to ``held_back`` (module docstring)."""
    if not degraded:
        return tuple(features), tuple(held_back)
    kept: list[MapFeature] = []
    back = list(held_back)
    for f in features:
        trips = set(f.properties.get("trips", ()))
        bad = trips & degraded
        if not bad:
            kept.append(f)
            continue
        props = {
            **f.properties,
            "flags": sorted({*f.properties.get("flags", ()), DEGRADED_SUPPORT}),
            "degraded_trips": len(bad),
        }
        (back if bad == trips else kept).append(replace(f, properties=props))
    return tuple(kept), tuple(back)
