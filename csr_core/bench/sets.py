"""The benchmark's scenario sets (``csr bench --set``): which simulated fleets each names.
Import-light (no numpy, no scipy): the ``csr`` command reads the set names at every start."""

from __future__ import annotations

from dataclasses import dataclass

WORLDS = ("urban", "highway", "rural", "roundabout", "karlsruhe")
#: the fleet models of ``csr simulate --fleet`` (docs/simulator.md): every real map runs with both
FLEETS = ("a", "b")
#: the real maps the simulator ships (csr_core/sim/data): the main accuracy set
REAL_MAP_WORLDS = ("karlsruhe", "kashiwanoha", "carcarana", "a9", "newmarket")


@dataclass(frozen=True, slots=True)
class ScenarioSpec:
    world: str
    trips: int
    profile: str = "standard"
    seed: int = 1
    trip_length_m: float | None = None
    fleet: str = "a"  # the fleet model (csr simulate --fleet): a, or b (csr_core.sim.fleet_b)

    @property
    def name(self) -> str:
        length = f"-{int(self.trip_length_m)}m" if self.trip_length_m else ""
        fleet = "" if self.fleet == "a" else f"-fleet{self.fleet}"
        return f"{self.world}-{self.profile}{fleet}-{self.trips}x{length}-s{self.seed}"


#: names accepted by :func:`scenario_set` (``csr bench --set``)
SCENARIO_SETS = (
    "quick",
    "standard",
    "standard-seeds",
    "dense",
    "hard",
    "validator",
    "variants",
    "full",
    "toy",
    "real-maps",
    "real-maps-quick",
    "loops",
)
#: seeds of ``standard-seeds``: one seed's fleets are a small sample (seed 1 vs seeds 2-3 differ
#: by half in aligned ATE), so the reported figures average three
STANDARD_SEEDS = (1, 2, 3)
#: ``dense``: the alignment's accuracy targets are stated for ">= 10 trips per road". The standard fleets
#: (10 trips of 1.5 km) put a median of 2-8 trips on a place (``trips/place`` in the bench's
#: per-scenario table, ``bench.evaluate.trips_per_place``); these are the fewest trips, in tens,
#: that give each world a median of at least 10 (measured on seed 1: urban 10, highway 11,
#: rural 12, roundabout 12, Karlsruhe 11)
DENSE_TRIPS = {"urban": 40, "highway": 70, "rural": 40, "roundabout": 20, "karlsruhe": 20}
#: ``validator``: the validator's measurement on the hard profile (``csr bench-validator``),
#: the six fleets of 8 trips x 1.5 km it is always measured on (docs/topology.md),
#: so that its figures compare across runs: (world, seed)
VALIDATOR_FLEETS = (
    ("urban", 5),
    ("urban", 9),
    ("karlsruhe", 3),
    ("highway", 7),
    ("rural", 11),
    ("roundabout", 2),
)
#: ``variants``: the fleets ``csr bench-variants`` rewrites into foreign ones; small, and in the two
#: compact worlds, where 6 trips of 800 m meet each other (the highway and rural worlds are large
#: enough that such a fleet barely overlaps, and its accuracy is its GNSS's)
VARIANT_FLEETS = (("urban", 6, 800.0), ("roundabout", 6, 800.0))


def scenario_set(name: str) -> list[ScenarioSpec]:
    if name == "quick":
        return [
            ScenarioSpec("urban", 6, "standard", 1, 800.0),
            ScenarioSpec("highway", 6, "standard", 1, 800.0),
        ]
    if name == "standard":
        return [ScenarioSpec(w, 10, "standard", 1, 1500.0) for w in WORLDS]
    if name == "standard-seeds":  # the same worlds and fleet sizes, three draws of traffic and noise
        return [ScenarioSpec(w, 10, "standard", seed, 1500.0) for seed in STANDARD_SEEDS for w in WORLDS]
    if name == "dense":  # the targets' condition, >= 10 trips per road
        return [ScenarioSpec(w, DENSE_TRIPS[w], "standard", 1, 1500.0) for w in WORLDS]
    if name == "hard":
        return [ScenarioSpec(w, 10, "hard", 1, 1500.0) for w in WORLDS]
    if name == "validator":
        return [ScenarioSpec(w, 8, "hard", seed, 1500.0) for w, seed in VALIDATOR_FLEETS]
    if name == "variants":
        return [ScenarioSpec(w, n, "standard", 1, length) for w, n, length in VARIANT_FLEETS]
    if name == "real-maps":  # every real map, both fleet models, standard and hard, three seeds
        return [
            ScenarioSpec(w, 10, profile, seed, 1500.0, fleet)
            for fleet in FLEETS
            for profile in ("standard", "hard")
            for seed in STANDARD_SEEDS
            for w in REAL_MAP_WORLDS
        ]
    if name == "real-maps-quick":  # one seed of the standard profile, both fleet models
        return [
            ScenarioSpec(w, 10, "standard", 1, 1500.0, fleet) for fleet in FLEETS for w in REAL_MAP_WORLDS
        ]
    if name == "loops":  # trips that lap short loops with long stops (the integrity test's case)
        return [ScenarioSpec(w, 8, "loops", 1, 2000.0) for w in ("roundabout", "urban", "kashiwanoha")]
    if name == "toy":
        return [ScenarioSpec("toy", 3, "toy", 1, 300.0)]
    if name == "full":
        return scenario_set("standard") + scenario_set("hard")
    raise ValueError(f"unknown scenario set {name!r} ({', '.join(SCENARIO_SETS)})")
