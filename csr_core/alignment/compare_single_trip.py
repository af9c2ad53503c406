"""What a single-trip setting does to the alignment: the stage run twice, both through ``align_trips``.

    python -m csr_core.alignment.compare_single_trip SCENARIO... --single-trip-param NAME=VALUE [...]
        [--param NAME=VALUE ...] [--cache DIR]

Per scenario, the single-trip stage runs as ``csr reconstruct`` does (``evaluate_failures.
single_trip_results``), once with its defaults and once with the given ``SingleTripParams``
fields changed; each result goes through :func:`csr_core.alignment.align_trips` in this process
(``--param`` changes ``AlignmentParams`` for both). Printed per scenario and as a mean over them,
for the default (``a``) and the changed (``b``) stage:

- ``trip-aligned``: each trip's smoothed poses against its truth after the trip's own SE(2), then
  the mean over the trips: the within-trip shape, what the single-trip rigid-offset figure depends on;
- ``aligned``: the contract's ATE (section 6) of the aligned poses.

A setting can win the first and lose the second: the alignment's models (Eq. 10-12's GNSS priors,
the e^sm chain) were fitted to the default stage's error shape (docs/single-trip.md).
``--cache`` keeps each variant's single-trip results (one file per scenario and params).
"""

from __future__ import annotations

import argparse
import sys
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from csr_core.alignment import align_trips
from csr_core.alignment.evaluate_failures import single_trip_results
from csr_core.alignment.evaluate_floor import ate_rmse_m, true_poses
from csr_core.alignment.params import DEFAULT as ALIGNMENT_DEFAULT
from csr_core.alignment.params import AlignmentParams
from csr_core.param_overrides import replace_fields
from csr_core.single_trip.params import DEFAULT as SINGLE_TRIP_DEFAULT
from csr_core.single_trip.params import SingleTripParams


@dataclass(frozen=True, slots=True)
class VariantScore:
    trip_aligned_ate_m: float  # mean over trips of the smoothed poses' ATE after each trip's own SE(2)
    aligned_ate_m: float  # contract ATE of the aligned poses


def score_variant(
    scenario: Path, cache: Path | None, single_trip: SingleTripParams, alignment: AlignmentParams
) -> VariantScore:
    frame, recons = single_trip_results(scenario, cache, single_trip)
    truth = true_poses(scenario, frame, [r.trip.key for r in recons])
    own = [ate_rmse_m({r.trip.key: r.poses_xyyaw_world}, {r.trip.key: truth[r.trip.key]}) for r in recons]
    result = align_trips(recons, params=alignment)
    return VariantScore(float(np.mean(own)), ate_rmse_m(result.poses_xyyaw_world, truth))


def compare(
    scenarios: Sequence[Path],
    changed: SingleTripParams,
    cache: Path | None = None,
    alignment: AlignmentParams = ALIGNMENT_DEFAULT,
    progress: Callable[[str], None] | None = None,
) -> list[tuple[str, VariantScore, VariantScore]]:
    """``(scenario name, default stage's scores, changed stage's scores)`` per scenario;
    ``progress`` hears one line per scenario done."""
    rows = []
    for k, s in enumerate(scenarios, 1):
        rows.append(
            (
                s.name,
                score_variant(s, cache, SINGLE_TRIP_DEFAULT, alignment),
                score_variant(s, cache, changed, alignment),
            )
        )
        if progress:
            progress(
                f"{k}/{len(scenarios)} {s.name}: aligned {rows[-1][1].aligned_ate_m:.4f} / "
                f"{rows[-1][2].aligned_ate_m:.4f} m"
            )
    return rows


def table(rows: Sequence[tuple[str, VariantScore, VariantScore]]) -> str:
    lines = ["| scenario | trip-aligned a / b [m] | aligned a / b [m] |", "| --- | --- | --- |"]
    for name, a, b in rows:
        lines.append(
            f"| {name} | {a.trip_aligned_ate_m:.4f} / {b.trip_aligned_ate_m:.4f} "
            f"| {a.aligned_ate_m:.4f} / {b.aligned_ate_m:.4f} |"
        )
    if rows:
        mean = [
            np.mean([getattr(r[k], f) for r in rows])
            for f in ("trip_aligned_ate_m", "aligned_ate_m")
            for k in (1, 2)
        ]
        lines.append(
            f"| mean of {len(rows)} | {mean[0]:.4f} / {mean[1]:.4f} | {mean[2]:.4f} / {mean[3]:.4f} |"
        )
    return "\n".join(lines)


def _to_stderr(line: str) -> None:
    sys.stderr.write(line + "\n")


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(
        prog="python -m csr_core.alignment.compare_single_trip",
        description=__doc__,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    ap.add_argument("scenarios", type=Path, nargs="+", help="scenario folders (trips/, truth/)")
    ap.add_argument(
        "--single-trip-param",
        action="append",
        default=[],
        metavar="NAME=VALUE",
        required=True,
        help="a SingleTripParams field to change for variant b (repeatable)",
    )
    ap.add_argument(
        "--param",
        action="append",
        default=[],
        metavar="NAME=VALUE",
        help="an AlignmentParams field to change for both variants (repeatable)",
    )
    ap.add_argument("--cache", type=Path, help="folder for cached single-trip results")
    args = ap.parse_args(argv)
    try:
        changed = replace_fields(SINGLE_TRIP_DEFAULT, args.single_trip_param)
        alignment = replace_fields(ALIGNMENT_DEFAULT, args.param)
    except ValueError as e:
        ap.error(str(e))
    missing = [str(s) for s in args.scenarios if not (s / "truth" / "poses").is_dir()]
    if missing:
        ap.error(f"not a scenario folder with truth/poses: {', '.join(missing)}")
    rows = compare(args.scenarios, changed, args.cache, alignment, progress=_to_stderr)
    sys.stdout.write(table(rows) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
