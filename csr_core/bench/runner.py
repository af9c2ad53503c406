"""`csr bench`: named scenario sets -> simulated scenarios (cached) -> `csr reconstruct` per method
(as a subprocess: the benchmark reaches the pipeline only through the command, which also gives
honest wall time and peak memory) -> evaluation (contract section 6) -> records.

Scenario sets (deterministic seeds; generated with ``csr simulate`` into ``OUT/scenarios``):

- ``quick``: urban and highway, standard profile, 6 trips of 800 m (CI speed).
- ``standard``: every world, standard profile, 10 trips of 1.5 km.
- ``hard``: every world, hard profile, 10 trips of 1.5 km.
- ``full``: standard + hard.
- ``toy``: the hand-made toy road of :mod:`csr_core.bench.toy` (3 trips of 300 m), written
  in-process rather than simulated: a seconds-long smoke run of the whole bench.
"""

from __future__ import annotations

import logging
import os
import shutil
import subprocess
import sys
import threading
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import TypeVar

import orjson

from csr_core.bench.evaluate import EvaluatedOutput, evaluate_output
from csr_core.bench.sets import ScenarioSpec, scenario_set
from csr_core.errors import CsrError

log = logging.getLogger(__name__)

METHODS = ("pipeline", "gnss_only", "roadmap_icp")
ABLATIONS = {"coarse only": ["--no-fine"], "fine only": ["--no-coarse"], "coarse + fine": []}


def csr_command() -> list[str]:
    """How to run the ``csr`` command from here (the venv's console script when present)."""
    script = Path(sys.executable).parent / "csr"
    if script.exists():
        return [str(script)]
    found = shutil.which("csr")
    if found:
        return [found]
    return [sys.executable, "-c", "import sys; from services.cli import main; sys.exit(main())"]


@dataclass(frozen=True, slots=True)
class CommandRun:
    returncode: int
    wall_s: float
    peak_rss_mb: float
    stderr_tail: str


def run_measured(argv: Sequence[str]) -> CommandRun:
    """Run a command; its wall time and its own peak resident memory (``wait4`` rusage)."""
    t0 = time.perf_counter()
    proc = subprocess.Popen(list(argv), stdout=subprocess.PIPE, stderr=subprocess.PIPE)
    # Drain pipes while waiting: communicate() would reap the child and lose its rusage.
    chunks: dict[str, bytes] = {}

    def drain(name: str, stream) -> None:
        chunks[name] = stream.read()

    threads = [
        threading.Thread(target=drain, args=(n, s)) for n, s in (("out", proc.stdout), ("err", proc.stderr))
    ]
    for t in threads:
        t.start()
    _, status, rusage = os.wait4(proc.pid, 0)
    wall = time.perf_counter() - t0
    for t in threads:
        t.join()
    proc.returncode = os.waitstatus_to_exitcode(status)
    err = chunks.get("err", b"").decode(errors="replace")
    return CommandRun(
        proc.returncode, wall, rusage.ru_maxrss / 1024.0, "\n".join(err.strip().splitlines()[-5:])
    )


def sources_fingerprint(*parts: str) -> str:
    """8 hex digits of a hash of ``csr_core``'s sources named by ``parts``, each a package
    (``"sim"``: all its modules) or a module (``"types.py"``): a cache keyed by it never serves
    results of other code."""
    import hashlib

    core = Path(__file__).resolve().parents[1]
    digest = hashlib.sha1()
    for part in parts:
        path = core / part
        for source in [path] if path.is_file() else sorted(path.rglob("*.py")):
            digest.update(source.read_bytes())
    return digest.hexdigest()[:8]


def simulator_fingerprint() -> str:
    """The simulator's :func:`sources_fingerprint`: the scenario cache is keyed by it, so a
    changed simulator never serves stale scenarios."""
    return sources_fingerprint("sim")


_Item = TypeVar("_Item")
_Result = TypeVar("_Result")


def reference_cpu_seconds(repeats: int = 3) -> float:
    """CPU seconds (best of ``repeats``) of a fixed workload of plain Python and numpy, the kind
    of work the single-trip stage does: the machines these benchmarks run on differ by more than
    2x from one day to the next (BENCHMARKS.md, machine reference), so a CPU figure is read
    against this one, measured beside it."""
    import numpy as np

    best = float("inf")
    for _ in range(repeats):
        t0 = time.process_time()
        sum(i * i for i in range(1_000_000))
        values = np.random.default_rng(0).random(500_000)
        for _ in range(20):
            np.sort(values)
        best = min(best, time.process_time() - t0)
    return best


def map_in_processes(
    fn: Callable[[_Item], _Result],
    items: Sequence[_Item],
    jobs: int,
    progress: Callable[[str], None] | None = None,
    label: Callable[[_Result], str] = str,
) -> list[_Result]:
    """``[fn(item) for item in items]`` in ``jobs`` worker processes (results in ``items``
    order), reporting "evaluated k/n: label(result)" as each one comes back."""
    from concurrent.futures import ProcessPoolExecutor

    results: list[_Result] = []
    with ProcessPoolExecutor(max_workers=max(1, jobs)) as pool:
        for done, result in enumerate(pool.map(fn, items), 1):
            results.append(result)
            if progress:
                progress(f"evaluated {done}/{len(items)}: {label(result)}")
    return results


def ensure_scenario(spec: ScenarioSpec, cache_dir: Path, fingerprint: str | None = None) -> Path:
    """The scenario folder for ``spec``, simulated with ``csr simulate`` unless cached (cache key:
    the spec and :func:`simulator_fingerprint`)."""
    fingerprint = fingerprint or simulator_fingerprint()
    out = cache_dir / (spec.name if spec.world == "toy" else f"{spec.name}-sim{fingerprint}")
    if (out / "scenario.json").exists() and (out / "truth" / "map.geojson").exists():
        return out
    if out.exists():
        shutil.rmtree(out)
    if spec.world == "toy":
        from csr_core.bench.toy import ToySpec, write_toy_scenario

        return write_toy_scenario(
            out, ToySpec(n_trips=spec.trips, length_m=spec.trip_length_m or 300.0, seed=spec.seed)
        )
    argv = csr_command() + [
        "simulate",
        "--world",
        spec.world,
        "--trips",
        str(spec.trips),
        "--profile",
        spec.profile,
        "--seed",
        str(spec.seed),
        "--out",
        str(out),
    ]
    if spec.trip_length_m:
        argv += ["--trip-length-m", str(spec.trip_length_m)]
    if spec.fleet != "a":
        argv += ["--fleet", spec.fleet]
    log.info("simulating %s", spec.name)
    run = run_measured(argv)
    if run.returncode != 0:
        raise CsrError(f"csr simulate failed for {spec.name} (exit {run.returncode}): {run.stderr_tail}")
    return out


@dataclass(frozen=True, slots=True)
class Record:
    """One method on one scenario: the evaluation and the costs."""

    scenario: str
    scenario_dir: Path
    world: str
    profile: str
    method: str
    variant: str  # "" or an ablation name
    run: CommandRun
    uploaded_bytes: int
    output_bytes: int
    km: float
    report: dict
    evaluated: EvaluatedOutput | None = field(default=None, repr=False)

    @property
    def ok(self) -> bool:
        return self.run.returncode == 0 and self.evaluated is not None

    @property
    def ev(self) -> EvaluatedOutput:
        """The evaluation of a run that succeeded (check :attr:`ok` first)."""
        if self.evaluated is None:
            raise CsrError(f"{self.scenario} {self.method}: the run failed, nothing to evaluate")
        return self.evaluated


def _dir_bytes(path: Path) -> int:
    return sum(p.stat().st_size for p in path.rglob("*") if p.is_file())


RUN_FILE = "bench_run.json"  # the measured command run, kept next to its outputs for --reuse-runs


def run_method(
    scenario_dir: Path,
    out_dir: Path,
    method: str,
    extra: Sequence[str] = (),
    variant: str = "",
    spec: ScenarioSpec | None = None,
    reuse: bool = False,
) -> Record:
    """``csr reconstruct`` one method on one scenario and evaluate it. With ``reuse``, a previous
    successful run in ``out_dir`` (same command) is evaluated again instead of re-run."""
    argv = csr_command() + [
        "reconstruct",
        str(scenario_dir),
        "--out",
        str(out_dir),
        "--method",
        method,
        "--no-progress",
        *extra,
    ]
    run_file = out_dir / RUN_FILE
    previous = orjson.loads(run_file.read_bytes()) if reuse and run_file.exists() else None
    if previous and previous["returncode"] == 0 and previous["argv"][1:] == argv[1:]:
        run = CommandRun(0, previous["wall_s"], previous["peak_rss_mb"], "")
    else:
        if out_dir.exists():
            shutil.rmtree(out_dir)
        run = run_measured(argv)
        out_dir.mkdir(parents=True, exist_ok=True)
        run_file.write_bytes(
            orjson.dumps(
                {
                    "argv": argv,
                    "returncode": run.returncode,
                    "wall_s": run.wall_s,
                    "peak_rss_mb": run.peak_rss_mb,
                }
            )
        )
    uploaded = sum(p.stat().st_size for p in (scenario_dir / "trips").glob("*.json.gz"))
    evaluated, report = None, {}
    if run.returncode == 0:
        report = orjson.loads((out_dir / "report.json").read_bytes())
        evaluated = evaluate_output(scenario_dir, out_dir)
    else:
        log.error("csr reconstruct --method %s failed on %s: %s", method, scenario_dir.name, run.stderr_tail)
    return Record(
        scenario=spec.name if spec else scenario_dir.name,
        scenario_dir=scenario_dir,
        world=spec.world if spec else scenario_dir.name,
        profile=spec.profile if spec else "",
        method=method,
        variant=variant,
        run=run,
        uploaded_bytes=uploaded,
        output_bytes=(
            _dir_bytes(out_dir / "poses") + (out_dir / "map.geojson").stat().st_size
            if run.returncode == 0
            else 0
        ),
        km=evaluated.trip_length_km if evaluated else float("nan"),
        report=report,
        evaluated=evaluated,
    )


def run_bench(
    set_name: str,
    out_root: Path,
    methods: Sequence[str] = METHODS,
    ablation: bool = True,
    progress: Callable[[str], None] | None = None,
    reuse: bool = False,
) -> list[Record]:
    """Simulate (cached), reconstruct with every method and evaluate. Records in set order."""
    records: list[Record] = []
    fingerprint = simulator_fingerprint()  # one per bench run, even if the simulator is edited meanwhile
    for spec in scenario_set(set_name):
        scenario_dir = ensure_scenario(spec, out_root / "scenarios", fingerprint)
        for method in methods:
            if progress:
                progress(f"{spec.name}: {method}")
            records.append(
                run_method(
                    scenario_dir, out_root / "runs" / spec.name / method, method, spec=spec, reuse=reuse
                )
            )
        pipeline = next((r for r in records if r.scenario == spec.name and r.method == "pipeline"), None)
        stages = set(pipeline.report.get("diagnostics", {}).get("stages", [])) if pipeline else set()
        if ablation and {"coarse", "fine"} <= stages:
            for variant, extra in ABLATIONS.items():
                if not extra:
                    continue
                if progress:
                    progress(f"{spec.name}: pipeline ({variant})")
                slug = variant.replace(" ", "_")
                records.append(
                    run_method(
                        scenario_dir,
                        out_root / "runs" / spec.name / f"pipeline-{slug}",
                        "pipeline",
                        extra,
                        variant,
                        spec,
                        reuse,
                    )
                )
    return records
