"""Fleet b: a second fleet model (GNSS, odometry, BEV perception), written from the upload
contract and the sensor literature, independent of fleet a (``csr_core.sim.gnss``,
``odometry``, ``perception``). Routes and driving are shared; ``simulate_scenario(...,
fleet="b")`` and ``csr simulate --fleet b`` select it. See ``docs/simulator.md``, "Fleet b".
"""

from csr_core.sim.fleet_b.params import FleetBParams
from csr_core.sim.fleet_b.trip import TripB, VehicleB, draw_vehicle_b, simulate_trip_b

__all__ = ["FleetBParams", "TripB", "VehicleB", "draw_vehicle_b", "simulate_trip_b"]
