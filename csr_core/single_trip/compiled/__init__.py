"""Compiled steps of the splicing stage (numba), one module per step.

A trip has about 300 tracks, and in numpy each track's splice is 300-500 small array calls of a
few microseconds each, none of them more than a fifth of the time (docs/single-trip.md):
the cost is the number of calls, not any one of them. Compiling one leaf saved 3 %;
these kernels compile whole steps (a projection with its nearest-point search, a
clustering with its labelling, a profile fit with its medians, ends and resampling), each one call.

Each kernel computes what the numpy code it replaced computed, in the same order, so that the
splices are the same to rounding (``tests/unit/test_single_trip_compiled.py`` checks them against
plain numpy and scipy). Compiled on first use and cached on disk (``cache=True``: beside this
file, or numba's user cache directory where that is read-only).
"""
