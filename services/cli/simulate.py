"""`csr simulate`: write a simulated fleet scenario folder (contract section 5).

csr simulate --world urban --trips 20 --profile standard --seed 1 --out scen/urban [--trip-length-m 2000] [--plot]
             [--fleet a|b]
"""

from __future__ import annotations

import argparse
import sys
import time

WORLDS = (
    "urban",
    "highway",
    "rural",
    "roundabout",
    "karlsruhe",
    "kashiwanoha",
    "carcarana",
    "a9",
    "newmarket",
)  # csr_core.sim.WORLD_NAMES
PROFILES = ("standard", "hard", "noiseless", "loops")
FLEETS = ("a", "b")  # csr_core.sim.scenario.FLEETS


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("simulate", help="simulate a fleet of trips on a world and write a scenario folder")
    p.add_argument(
        "--world",
        required=True,
        choices=WORLDS,
        help="procedural world or real map (Lanelet2, CommonRoad, OpenDRIVE)",
    )
    p.add_argument("--trips", type=int, required=True, help="number of trips")
    p.add_argument("--profile", default="standard", choices=PROFILES, help="sensor error profile")
    p.add_argument("--seed", type=int, default=0, help="random seed (same seed: byte-identical output)")
    p.add_argument("--out", required=True, help="scenario folder to write")
    p.add_argument("--trip-length-m", type=float, default=2000.0, help="length of each trip (metres)")
    p.add_argument(
        "--fleet",
        default="a",
        choices=FLEETS,
        help="fleet model: a (profiles.py models, --profile applies) or b (csr_core.sim.fleet_b, its own parameters)",
    )
    p.add_argument("--plot", action="store_true", help="also draw OUT/overview.png (truth map and trips)")
    p.set_defaults(func=_run)


def _run(args: argparse.Namespace) -> int:
    from pathlib import Path

    from tqdm import tqdm

    from csr_core.sim import simulate_scenario

    if args.trips < 1:
        raise SystemExit("csr simulate: --trips must be at least 1")
    started = time.perf_counter()
    trajectories = []
    with tqdm(total=args.trips, desc=f"simulate {args.world}", unit="trip", file=sys.stderr) as bar:

        def progress(trip) -> None:
            if args.plot:
                trajectories.append(trip.true_poses_xyyaw_world[:, :2])
            bar.update(1)

        scenario = simulate_scenario(
            args.world,
            args.trips,
            args.profile,
            args.seed,
            args.out,
            trip_length_m=args.trip_length_m,
            progress=progress,
            fleet=args.fleet,
        )
    if args.plot:
        from csr_core.sim import load_world
        from csr_core.sim.plot import plot_world

        plot_world(load_world(args.world), Path(args.out) / "overview.png", trajectories)
    trips = scenario["trips"]
    km = sum(t["length_m"] for t in trips) / 1000.0
    frames = sum(t["frames"] for t in trips)
    print(
        f"csr simulate: {scenario['name']}: {len(trips)} trips, {km:.1f} km, {frames} frames "
        f"-> {args.out} in {time.perf_counter() - started:.1f} s"
    )
    return 0
