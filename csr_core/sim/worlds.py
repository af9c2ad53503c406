"""World registry: ``load_world(name)`` for the names ``csr simulate --world`` accepts."""

from __future__ import annotations

import functools
from collections.abc import Callable

from csr_core.sim.world import SimulationError, World

WORLD_NAMES = (
    "urban",
    "highway",
    "rural",
    "roundabout",
    "karlsruhe",
    "kashiwanoha",
    "carcarana",
    "a9",
    "newmarket",
)


def _builders() -> dict[str, Callable[[], World]]:
    from csr_core.sim import commonroad_world, lanelet2_world, opendrive_world, worlds_procedural

    return {
        "urban": worlds_procedural.urban_grid,
        "highway": worlds_procedural.highway,
        "rural": worlds_procedural.rural,
        "roundabout": worlds_procedural.roundabout,
        "karlsruhe": lanelet2_world.karlsruhe,
        "kashiwanoha": lanelet2_world.kashiwanoha,
        "carcarana": commonroad_world.carcarana,
        "a9": commonroad_world.a9,
        "newmarket": opendrive_world.newmarket,
    }


@functools.lru_cache(maxsize=8)
def load_world(name: str) -> World:
    """The named world (built once per process; treat it as read-only)."""
    builders = _builders()
    if name not in builders:
        raise SimulationError(f"unknown world {name!r}; known: {', '.join(WORLD_NAMES)}")
    return builders[name]()
