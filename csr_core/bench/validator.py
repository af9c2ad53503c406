"""The validator benchmark: recall and precision of the suspect flags on the hard profile.

``csr bench-validator`` runs :func:`csr_core.topology.evaluate.evaluate_scenario` with the
aligned poses (single-trip stage, ``align_trips``, then ``generate_topology`` with the
alignment's match pairs, as the pipeline runs them) on every fleet of the ``validator`` set and
pools what ``validator_scores`` reports: an instance is really wrong when at least a fifth of
its 0.5 m samples are more than 0.5 m from the truth, flagged when it carries a suspect flag.
This module holds the target, the run and the tables; the command writes them.
"""

from __future__ import annotations

import os
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from csr_core.bench.runner import (
    ensure_scenario,
    map_in_processes,
    simulator_fingerprint,
    sources_fingerprint,
)
from csr_core.bench.sets import ScenarioSpec, scenario_set
from csr_core.bench.tables import duration_text, markdown_table
from csr_core.topology.validation import SEVERITY, SUSPECT
from csr_core.topology.validator_reach import (
    TRIPS_AGREE,
    evidence_table,
    learned_reach,
    trip_comparison_recall_ceiling,
)

SECTION = "validator"
RECALL_MIN = 0.8  # the target: recall >= 0.8 at precision >= 0.5
PRECISION_MIN = 0.5
#: the suspect flags, most severe first, as the section lists them
SUSPECT_ORDER = sorted(SUSPECT, key=lambda kind: (-SEVERITY[kind], kind))
#: what the cached per-fleet instances depend on: the single-trip stage, the alignment, the
#: instances moved with it (``topology.instances.reposition_instances``) and the core's types,
#: frames and upload decoding
ALIGNMENT_CACHE_SOURCES = (
    "single_trip",
    "alignment",
    "topology/instances.py",
    "types.py",
    "se2.py",
    "geo.py",
    "upload.py",
    "scenario.py",
)


@dataclass(frozen=True, slots=True)
class Job:
    spec: ScenarioSpec
    scenario_dir: Path
    cache: Path
    figure: Path | None


def _evaluate(job: Job) -> dict:
    """One fleet (a worker process): the topology evaluation with the aligned poses."""
    from csr_core.topology.evaluate import evaluate_scenario

    cached = job.cache.exists()
    r = evaluate_scenario(
        job.scenario_dir,
        poses="aligned",
        cache=str(job.cache),
        validator_figure=job.figure,
        figure_bbox_xy=None,
        keep_instances=True,
    )
    return {
        "spec": job.spec.name,
        "world": job.spec.world,
        "seed": job.spec.seed,
        "trips": r["trips"],
        "mcd": r["fused"]["mcd"],
        "validator": r["validator"],
        "instances": r["instances"],
        "figure": str(job.figure) if job.figure else None,
        "cached": cached,
    }


def run_validator_bench(
    cache_dir: Path,
    work_dir: Path,
    set_name: str = "validator",
    jobs: int = 2,
    figure_for: str | None = "karlsruhe",
    figure_dir: Path | None = None,
    progress: Callable[[str], None] | None = None,
) -> list[dict]:
    """Every fleet of ``set_name`` (simulated unless cached in ``cache_dir``; the single-trip and
    alignment results cached in ``work_dir``, keyed by ``ALIGNMENT_CACHE_SOURCES``), evaluated in
    ``jobs`` processes. The first fleet of world ``figure_for`` (or the first fleet, if the set
    has none) is also drawn into ``figure_dir``."""
    fingerprint = simulator_fingerprint()
    code = sources_fingerprint(*ALIGNMENT_CACHE_SOURCES)
    work_dir.mkdir(parents=True, exist_ok=True)
    work, drawn = [], False
    specs = scenario_set(set_name)
    if figure_for is not None and all(s.world != figure_for for s in specs):
        figure_for = None
    for spec in specs:
        if progress:
            progress(f"scenario {spec.name}")
        figure = None
        if figure_dir is not None and not drawn and (figure_for is None or spec.world == figure_for):
            figure, drawn = figure_dir / "bench_validator_map.png", True
        scenario = ensure_scenario(spec, cache_dir, fingerprint)
        work.append(Job(spec, scenario, work_dir / f"{scenario.name}-aligned-{code}.pkl", figure))
    return map_in_processes(_evaluate, work, jobs, progress, label=lambda r: r["spec"])


def pooled(results: Sequence[dict], key: str | None = None) -> dict:
    """Recall and precision over all fleets (instances pooled, not fleets averaged); ``key``:
    ``beyond_local_offset`` for those figures."""
    wrong = flagged = caught = 0
    for r in results:
        v = r["validator"] if key is None else r["validator"][key]
        wrong += v["wrong"]
        flagged += v["flagged"]
        caught += round(v["recall"] * v["wrong"])
    return {
        "wrong": wrong,
        "flagged": flagged,
        "caught": caught,
        "recall": caught / wrong if wrong else float("nan"),
        "precision": caught / flagged if flagged else float("nan"),
    }


def _share(v: float) -> str:
    return f"{v:.3f}" if v == v else "n/a"


def reach_of(results: Sequence[dict], served: dict | None = None) -> dict | None:
    """What a validator can reach on the fleets' judged instances (``topology.validator_reach``):
    the evidence table, the recall without the instances agreeing trips saw, the classifiers
    trained on the other fleets (None with fewer than two fleets) and the flags as served
    (``served``: ``pooled(results)``, if already at hand); None when the results carry no instances."""
    rows = [row for r in results for row in r.get("instances", ())]
    if not rows:
        return None
    fleets = [r["spec"] for r in results for _ in r.get("instances", ())]
    table = evidence_table(rows)
    learned = learned_reach(rows, fleets, RECALL_MIN, PRECISION_MIN) if len(set(fleets)) >= 2 else None
    return {
        "table": table,
        "ceiling": trip_comparison_recall_ceiling(table),
        "learned": learned,
        "served": served if served is not None else pooled(results),
    }


def reach_lines(reach: dict | None, figure: Path | None = None, doc_dir: Path | None = None) -> list[str]:
    """The section's part on what a validator can reach (``reach_of``); nothing for None."""
    if reach is None:
        return []
    table = reach["table"]
    wrong = sum(t["wrong"] for t in table.values())
    class_rows = [
        [
            name,
            str(t["instances"]),
            str(t["wrong"]),
            f"{t['wrong'] / t['instances']:.3f}" if t["instances"] else "n/a",
            str(t["flagged"]),
            str(t["caught"]),
        ]
        for name, t in table.items()
    ]
    agree = table[TRIPS_AGREE]
    lines = [
        "### What a validator can reach here",
        "",
        "Where the wrong instances are, by what their trips say of them (`topology.validator_reach`: *one trip* "
        "saw it; two or more *disagree* by the `high_variance` or `trips_disagree` rule; two or more *agree* "
        "within their own noise):",
        "",
        markdown_table(
            ["evidence", "instances", "wrong", "share wrong", "flagged", "flagged and wrong"], class_rows
        ),
        "",
        f"- {agree['wrong']} of the {wrong} wrong instances are instances that two or more trips agree on within "
        f"their noise: an error all their trips share, which no comparison of trips shows. A validator that "
        f"caught every other wrong instance and flagged none of the {agree['instances']} agreeing ones "
        f"({agree['wrong'] / max(agree['instances'], 1):.1%} of them wrong) would reach recall "
        f"{_share(reach['ceiling'])}.",
    ]
    if reach["learned"] is not None:
        said = "; ".join(
            f"{model}: precision {_share(v['precision_at_recall'])} at recall >= {RECALL_MIN}, "
            f"recall {_share(v['recall_at_precision'])} at precision >= {PRECISION_MIN}"
            for model, v in reach["learned"].items()
        )
        lines += [
            f"- A classifier trained on the truth's verdicts and every property the map serves per instance "
            f"(support, coverage, trips that drove alongside, uncertainty, scatter, length, type, the flags), "
            f"on all fleets but one and scored on the one left out, pooled over the fleets, at its best "
            f"threshold: {said}."
        ]
    lines.append("")
    if figure is not None and doc_dir is not None:
        rel = Path(os.path.relpath(Path(figure).resolve(), Path(doc_dir).resolve()))
        lines += [
            f"![What a validator can reach: the flags, the classifiers, the bound]({rel.as_posix()})",
            "",
        ]
    return lines


def plot_reach(reach: dict, out_png: Path) -> None:
    """Precision against recall: the flags as served, the classifiers' held-out curves, the
    recall without the instances agreeing trips saw, and the target bound (shaded)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(7, 5.5))
    ax.fill_between(
        [RECALL_MIN, 1.0],
        PRECISION_MIN,
        1.0,
        color="tab:green",
        alpha=0.12,
        label=f"target bound (recall >= {RECALL_MIN}, precision >= {PRECISION_MIN})",
    )
    for (model, v), color in zip((reach["learned"] or {}).items(), ("tab:blue", "tab:purple"), strict=False):
        rec, prec = v["curve"]
        ax.step(rec, prec, where="post", color=color, lw=1.3, label=f"{model}, trained on the other fleets")
    if reach["ceiling"] == reach["ceiling"]:
        ax.axvline(
            reach["ceiling"],
            color="0.4",
            ls="--",
            lw=1.0,
            label="recall without the instances agreeing trips saw",
        )
    served = reach["served"]
    ax.plot(
        [served["recall"]], [served["precision"]], "o", color="tab:red", ms=8, label="the flags as served"
    )
    ax.set_xlim(0, 1)
    ax.set_ylim(0, 1)
    ax.set_xlabel("recall (wrong instances flagged)")
    ax.set_ylabel("precision (flagged instances wrong)")
    ax.set_title("What a validator can reach on these fleets")
    ax.legend(loc="lower left", fontsize=8)
    ax.grid(alpha=0.3)
    out_png.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(out_png, dpi=90, bbox_inches="tight")
    plt.close(fig)


def render_section(
    results: Sequence[dict],
    figure: Path | None,
    doc_dir: Path,
    elapsed_s: float,
    set_name: str = "validator",
    reach_figure: Path | None = None,
) -> str:
    """The markdown of BENCHMARKS.md's validator section; ``reach_figure``: also draw what a
    validator can reach there (``plot_reach``) and show it."""
    n_cached = sum(bool(r.get("cached")) for r in results)
    cached = f", {n_cached} of {len(results)} fleets' alignments from the cache" if n_cached else ""

    total = pooled(results)
    local = pooled(results, "beyond_local_offset")
    met = total["recall"] >= RECALL_MIN and total["precision"] >= PRECISION_MIN  # False on n/a (NaN)
    instances = sum(r["validator"]["instances"] for r in results)
    fleets = ", ".join(f"`{r['spec']}`" for r in results)
    regenerate = "csr bench-validator --write BENCHMARKS.md" + (
        "" if set_name == "validator" else f" --set {set_name}"
    )
    lines = [
        "## Validator (`csr bench-validator`)",
        "",
        f"Regenerate: `{regenerate}` ({duration_text(elapsed_s)} on this machine{cached}; scenarios cached in "
        f"`bench-out/scenarios`, alignments in `bench-out/validator`, keyed by the sources they come from). "
        f"Measured "
        f"{time.strftime('%Y-%m-%d %H:%M UTC', time.gmtime())}. Set `{set_name}`: "
        f"{fleets} (simulator sources fingerprint `{simulator_fingerprint()}`). "
        "Each fleet: single-trip stage, `align_trips`, `generate_topology` with the alignment's match pairs (as "
        "`csr reconstruct` runs them), then every instance judged against the truth "
        "(`python -m csr_core.topology.evaluate DIR --poses aligned`): *wrong* when at least a fifth of its 0.5 m "
        "samples are more than 0.5 m from the truth of its type, *flagged* when it carries a suspect flag "
        f"({', '.join(f'`{k}`' for k in SUSPECT_ORDER)}).",
        "",
        f"**Pooled over {instances} instances: recall {_share(total['recall'])} ({total['caught']} of {total['wrong']} "
        f"wrong instances flagged), precision {_share(total['precision'])} ({total['caught']} of {total['flagged']} "
        f"flagged are wrong). The target bound, recall >= {RECALL_MIN} at precision >= {PRECISION_MIN}: "
        f"{'met' if met else 'not met'}.** Against the instances still wrong once the offset that the map around "
        f"them shares is removed (an error no comparison of trips can see): recall {_share(local['recall'])}, "
        f"precision {_share(local['precision'])}.",
        "",
    ]
    rows = []
    for r in results:
        v = r["validator"]
        rows.append(
            [
                r["spec"],
                str(r["trips"]),
                str(v["instances"]),
                str(v["wrong"]),
                str(v["flagged"]),
                _share(v["recall"] if v["wrong"] else float("nan")),
                _share(v["precision"] if v["flagged"] else float("nan")),
                f"{r['mcd']:.3f}",
            ]
        )
    lines += [
        markdown_table(
            ["fleet", "trips", "instances", "wrong", "flagged", "recall", "precision", "map mCD [m]"], rows
        ),
        "",
    ]
    kinds: dict[str, np.ndarray] = {}
    for r in results:
        for kind, c in r["validator"]["per_flag"].items():
            kinds[kind] = kinds.get(kind, np.zeros(4, int)) + np.array(
                [c["flagged"], c["wrong"], c["alone"], c["alone_wrong"]]
            )
    flag_rows = [
        [kind, str(c[0]), str(c[1]), f"{c[1] / max(c[0], 1):.2f}", str(c[2]), str(c[3])]
        for kind, c in sorted(kinds.items(), key=lambda kv: -kv[1][0])
    ]
    informative = ", ".join(f"`{k}`" for k in sorted(k for k, v in SEVERITY.items() if v == 0))
    lines += [
        "Per flag, pooled (an instance can carry several; *alone*: its only suspect flag; "
        f"{informative} are informative, not suspect):",
        "",
        markdown_table(
            ["flag", "instances", "of them wrong", "share wrong", "alone", "alone, wrong"], flag_rows
        )
        if flag_rows
        else "(no instance flagged)",
        "",
    ]
    reach = reach_of(results, total)
    if reach is not None and reach_figure is not None:
        plot_reach(reach, reach_figure)
    lines += reach_lines(reach, reach_figure if reach is not None else None, doc_dir)
    if figure is not None:
        rel = Path(os.path.relpath(Path(figure).resolve(), doc_dir.resolve()))
        lines += [f"![The validator on one fleet: caught, missed, false alarms]({rel.as_posix()})", ""]
    lines += [
        'How the flags were chosen and what was tried: docs/topology.md ("Validation" and "Tried and rejected").'
    ]
    return "\n".join(lines)
