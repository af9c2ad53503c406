"""Fleet simulator: worlds with a truth map and lane graph, routes, GNSS / odometry / BEV
perception models, and scenario folders (contract section 5). See ``docs/simulator.md``.

    from csr_core.sim import load_world, simulate_scenario
    simulate_scenario("urban", n_trips=20, profile="standard", seed=1, out_dir="scen/urban")
"""

from csr_core.sim.profiles import Profile, get_profile
from csr_core.sim.scenario import simulate_scenario
from csr_core.sim.world import SimulationError, TruthElement, World
from csr_core.sim.worlds import WORLD_NAMES, load_world

__all__ = [
    "SimulationError",
    "World",
    "TruthElement",
    "Profile",
    "get_profile",
    "load_world",
    "simulate_scenario",
    "WORLD_NAMES",
]
