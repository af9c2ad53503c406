"""Compile every kernel of the splicing stage now, into numba's disk cache (``warm_up``):

    python -m csr_core.single_trip.compiled

Compiling them all takes 30-40 s of CPU on first use; after that each process loads them from the
cache in about a second. ``make setup`` and the Docker build run this, so that the first trip a
worker or ``csr reconstruct`` takes does not pay for it. Two synthetic trips (a straight road with
dashes, a centreline, a stop line and a crosswalk; a bend) go through ``reconstruct_trip``, which
calls the kernels with the argument types it uses in production, and the kernels such simple roads
do not reach (backbone growth, the in-range test of the frames that missed an element, the
fusion's robust ends) are called through the same wrappers the pipeline uses. A kernel called
with other types later compiles that variant on its first use.
"""

from __future__ import annotations

import time

import numpy as np
from numba.core.registry import CPUDispatcher

from csr_core.single_trip import reconstruct_trip
from csr_core.single_trip.compiled import checks, growth, observations, polyline, profile, search
from csr_core.single_trip.splicing import _robust_ends, grow_backbone
from csr_core.single_trip.synthetic import SynthCrossing, SynthLine, SynthSpec, make_trip
from csr_core.types import DividerStyle, ElementType

_MODULES = (checks, growth, observations, polyline, profile, search)


def _warm_up_specs() -> list[SynthSpec]:
    lines = (
        SynthLine(ElementType.ROAD_BOUNDARY, -1.9),
        SynthLine(ElementType.LANE_DIVIDER, 1.75, style=DividerStyle.DASHED, dash_m=(3.0, 6.0)),
        SynthLine(ElementType.CENTERLINE, 3.5),
        SynthLine(ElementType.LANE_DIVIDER, 5.25, style=DividerStyle.SOLID),
        SynthLine(ElementType.ROAD_BOUNDARY, 8.9),
    )
    crossings = (
        SynthCrossing(ElementType.STOP_LINE, 150.0, -1.9, 5.25),
        SynthCrossing(ElementType.CROSSWALK, 160.0, -1.9, 8.9),
    )
    return [
        SynthSpec(
            length_m=250.0,
            element_sigma_m=0.03,
            gnss_sigma_m=0.3,
            odom_sigma_per_m=0.002,
            seed=1,
            lines=lines,
            crossings=crossings,
        ),
        SynthSpec(length_m=200.0, curvature_1pm=0.03, element_sigma_m=0.03, seed=2, lines=lines),
    ]


def _warm_up_rest() -> None:
    """The kernels the synthetic roads do not reach, through the pipeline's own wrappers."""
    arc = np.column_stack(
        [20.0 * np.sin(np.linspace(0.0, 0.8, 30)), 20.0 - 20.0 * np.cos(np.linspace(0.0, 0.8, 30))]
    )
    for follow_bends in (False, True):
        grow_backbone(arc, np.array([[0, 9], [10, 19], [20, 29]]), follow_bends=follow_bends)
    poses = np.column_stack([arc, np.zeros(len(arc))])
    checks.frames_in_range(arc[:5].copy(), poses[np.arange(3)], np.array([-15.0, 30.0, -15.0, 15.0]))
    _robust_ends(np.linspace(0.0, 10.0, 12), np.repeat(np.arange(3), 4))


def kernels() -> dict[str, CPUDispatcher]:
    """Every kernel defined in the package, by its qualified name."""
    return {
        f"{module.__name__.rsplit('.', 1)[-1]}.{name}": obj
        for module in _MODULES
        for name, obj in vars(module).items()
        if isinstance(obj, CPUDispatcher) and obj.py_func.__module__ == module.__name__
    }


def warm_up() -> float:
    """Compile every kernel, or load it from numba's cache, in this process; returns the CPU seconds
    it took. Timing code calls it before the clock starts, as it imports its modules first."""
    start = time.process_time()
    for spec in _warm_up_specs():
        trip, _, frame = make_trip(spec)
        reconstruct_trip(trip, frame)
    _warm_up_rest()
    return time.process_time() - start


def main() -> int:
    cpu_s = warm_up()
    n_compiled = sum(len(kernel.signatures) for kernel in kernels().values())
    print(  # noqa: T201
        f"csr_core.single_trip.compiled: {len(kernels())} kernels, {n_compiled} signatures compiled or "  # noqa: T201
        f"loaded from numba's cache in {cpu_s:.1f} CPU s"
    )
    return 0
