"""`make bench`: wall time and peak memory of the design per stage (ladder family, Cuk), and the closed loops.

Each measurement runs in a fresh process (`ashc design` on a generated spec), so imports, compilation and
memory are counted as a user sees them; peak memory is the child's maximum resident set size.  Prints two
tables (Markdown, ready for README):

1. the design per stage on the Cuk spec and the ladder family, with the fitted growth exponent of the time in
   n (least squares of log t on log n over the ladder sizes);
2. the closed loops and the large plants (issue 13): Cuk `simulate` and `falsify` with the compiled code's
   first run (an empty cache: numba compiles) and a cached run in a new process, 10,000 falsification runs,
   the ladder at n = 256 and 512, and `stabilise` with `decay_rate: maximise` at 64 states;
3. the contraction certificates (issue 20): the MORwiki RC ladder at N = 5..1000, a chain of 100 masses,
   an ill-conditioned ladder, the CSTR and the inverted pendulum, and the objectives rate and min_gain
   (with the falsified error over the bound);
4. large plants fast and proved (issue 44): T0, the bare import of the dependencies, and the switched ladder at
   n = 16..512 and three small nonlinear plants in multiples of T0, with their verdicts and the growth exponent;
5. tasks at the plant's speed (issue 45): for three tasks, when y is in each reach set with the budget, the governor
   and error-aware planning, and the abstraction's lower bound under the guarantee (bench/task_times.py).

With ``--against REV`` (``make bench BENCH_AGAINST=REV``) it prints only the closed loops of this tree and of the
git revision REV side by side (issue 40: a restructuring of the loops must keep their speed): Cuk ``simulate``,
the governor's ``simulate``, ``falsify`` of 3000 Cuk runs and ``tradeoff``, each in fresh processes, the two trees
in turn (A B A B ...) on the same design folder, the median of ``--pairs`` runs of each and the median of the
ratios pair by pair (a ratio holds when the machine's speed drifts).

    python bench/bench.py [--stages 1 2 4 8 16 32] [--timeout 900] [--runs 10000] [--no-closed-loops]
                          [--no-certificates | --only-certificates | --only-large | --only-tasks] [--against REV [--pairs 5]]
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from ashc_cli.design.pipeline import DESIGN

ROOT = Path(__file__).resolve().parents[1]
ASHC = [str(Path(sys.executable).with_name("ashc"))]
STAGES = DESIGN


#: A fresh wrapper per measurement, so RUSAGE_CHILDREN's maximum RSS is that of this one command.
WRAPPER = ("import resource, subprocess, sys; rc = subprocess.run(sys.argv[1:]).returncode; "
           "print('__MAXRSS_KIB__', resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss, file=sys.stderr); sys.exit(rc)")


def run_child(cmd: list[str], timeout: float, env: dict | None = None) -> tuple[float, float, str, int]:
    """Wall seconds, peak RSS (MiB) of the command, its stdout+stderr, its exit code."""
    start = time.perf_counter()
    proc = subprocess.run([sys.executable, "-c", WRAPPER, *cmd], capture_output=True, text=True, timeout=timeout, cwd=ROOT, env=env)
    wall = time.perf_counter() - start
    kib = [float(line.split()[1]) for line in proc.stderr.splitlines() if line.startswith("__MAXRSS_KIB__")]
    return wall, (kib[-1] / 1024.0 if kib else float("nan")), proc.stdout + proc.stderr, proc.returncode


def measure(case: str, n: int, cmd: list[str], timeout: float) -> dict:
    """One table row: ``ashc design`` in a fresh process (a timeout gives NaN and exit -1)."""
    try:
        wall, mem, text, rc = run_child(cmd, timeout)
    except subprocess.TimeoutExpired:
        wall, mem, text, rc = float("nan"), float("nan"), "", -1
    return {"case": case, "n": n, "total": wall, "mem": mem, "rc": rc, **parse_progress(text)}


def parse_progress(text: str) -> dict[str, float]:
    times = {}
    for line in text.splitlines():
        parts = line.split()
        if len(parts) > 3 and parts[0] in STAGES and parts[1] == "ran":
            times[parts[0]] = float(parts[2])
    return times


def stage_time(text: str, stage: str) -> float:
    """The seconds on the progress line "<stage> ran X s" (NaN when the stage did not run)."""
    for line in text.splitlines():
        parts = line.split()
        if len(parts) > 3 and parts[0] == stage and parts[1] == "ran":
            return float(parts[2])
    return float("nan")


def ladder_spec(folder: Path, stages: int, maximise: bool = False, task: bool = False) -> Path:
    """`ashc example ladder` written to folder (with ``decay_rate: maximise`` or its reach-avoid task when asked)."""
    path = folder / f"ladder_{stages}{'_max' if maximise else ''}{'_task' if task else ''}.yaml"
    subprocess.run(ASHC + ["example", "ladder", "--stages", str(stages), "--output", str(path)] + (["--task"] if task else []), check=True,
                   capture_output=True, cwd=ROOT)
    if maximise:
        import yaml

        spec = yaml.safe_load(path.read_text())
        spec["stabilisability"]["decay_rate"] = "maximise"
        path.write_text(yaml.safe_dump(spec, sort_keys=False, width=140))
    return path


def closed_loops(tmp: Path, timeout: float, runs: int) -> list[dict]:
    """The rows of issue 13's table: compiled closed loops (compile and cached), the large ladders and the
    maximised LMI.  Each command runs in a fresh process; ``ASHC_CACHE`` points at an empty folder first, so
    the first run compiles (numba) and the second, a new process, loads the cache."""
    env_cache = tmp / "cache"
    env = {**os.environ, "ASHC_CACHE": str(env_cache)}
    out = []

    def timed(label: str, cmd: list[str], stage: str, target: str, note: str = "") -> dict:
        try:
            wall, mem, text, rc = run_child(cmd, timeout, env)
        except subprocess.TimeoutExpired:
            wall, mem, text, rc = float("nan"), float("nan"), "", -1
        row = {"work": label, "stage": stage_time(text, stage), "wall": wall, "mem": mem, "rc": rc, "target": target, "note": note}
        out.append(row)
        print(f"  measured {label}: {row['stage']:.2f} s ({wall:.1f} s wall)", file=sys.stderr, flush=True)
        return row

    cuk = tmp / "cuk"
    spec = "specs/cuk_converter.yaml"
    subprocess.run(ASHC + ["design", spec, "--out", str(cuk)], check=True, capture_output=True, cwd=ROOT, env=env)
    timed("Cuk `simulate`, first run (compiles)", ASHC + ["simulate", spec, "--out", str(cuk), "--force"], "simulate", "compile <= 10 s")
    timed("Cuk `simulate`, cached (new process)", ASHC + ["simulate", spec, "--out", str(cuk), "--force"], "simulate", "<= 1.0 s")
    timed("Cuk `falsify` 12 runs x 1 s, first run (compiles)", ASHC + ["falsify", spec, "--out", str(cuk), "--runs", "12", "--t-final", "1"],
          "falsify", "compile <= 10 s")
    row = timed(f"Cuk `falsify` {runs} runs x 10 s, cached", ASHC + ["falsify", spec, "--out", str(cuk), "--runs", str(runs), "--t-final", "10"],
                "falsify", "10,000 runs <= 120 s")
    row["note"] = f"{runs / row['stage']:.0f} runs/s" if row["stage"] > 0 else ""
    for N in (64, 128):
        path = ladder_spec(tmp, N)
        timed(f"ladder n = {4 * N} `design`", ASHC + ["design", str(path), "--out", str(tmp / f"big{N}")], "bound",
              "<= 30 s" if N == 64 else "<= 90 s, <= 2 GiB")
        out[-1]["stage"] = out[-1]["wall"]    # the whole design is the work here
    task, tdir = "tests/specs/cuk_task.yaml", tmp / "cuk_task"
    design = timed("Cuk task `design` (tests/specs/cuk_task.yaml)", ASHC + ["design", task, "--out", str(tdir)], "bound", "")
    design["stage"] = design["wall"]
    row = timed("Cuk task `synthesize` (design up to date)", ASHC + ["synthesize", task, "--out", str(tdir)], "synthesize",
                "<= 3 x the design (issue 41)")
    row["note"] = f"{row['wall'] / design['wall']:.1f} x the design's wall time; " + task_split(tdir, task, timeout, env)
    out += grid_games(timeout)
    detour, ddir = "specs/two_output_detour.yaml", tmp / "detour"
    subprocess.run(ASHC + ["design", detour, "--out", str(ddir)], check=True, capture_output=True, cwd=ROOT, env=env)
    timed("detour `synthesize` (specs/two_output_detour.yaml): grid planner, 80 x 80 cells", ASHC + ["synthesize", detour, "--out", str(ddir)],
          "synthesize", "issue 42", "2 abstract states, 2 outputs, an avoid box to go around; proved")
    for N in (8, 128):      # the ladder's reach-avoid task (`ashc example ladder --task`): a 160 s plant run at the end
        path, folder = ladder_spec(tmp, N, task=True), tmp / f"task{N}"
        subprocess.run(ASHC + ["design", str(path), "--out", str(folder)], check=True, capture_output=True, cwd=ROOT, env=env)
        timed(f"ladder n = {4 * N} task `synthesize` (`ashc example ladder --stages {N} --task`): grid planner, 800 cells", ASHC + ["synthesize", str(path), "--out", str(folder)],
              "synthesize", "issue 42", "1 abstract state; proved; includes the plant run over the task's 160 s")
    path = ladder_spec(tmp, 16, maximise=True)
    timed("`stabilise` with decay_rate: maximise, 64 states", ASHC + ["stabilise", str(path), "--out", str(tmp / "max16")], "stabilise", "<= 60 s")
    return out


#: The planner's fixed points (issue 42) on grids of the sizes the issue names: transitions of a moving cell box
#: (each successor 3 cells wide per axis), ``safety`` over the steps (2-D) or ``pre`` repeated (3-D).
GRID_GAMES = ("import sys, time; import numpy as np; from ashc_cli.numerics.grid_games import Grid, Transitions, pre, safety; "
              "cells = tuple(int(c) for c in sys.argv[1].split('x')); reach = int(sys.argv[2]); steps = int(sys.argv[3]); d = len(cells); "
              "grid = Grid(np.zeros(d), np.ones(d), cells); moves = np.array(np.meshgrid(*[np.arange(-reach, reach + 1)] * d, indexing='ij')).reshape(d, -1).T; "
              "t0 = time.perf_counter(); idx = np.stack(np.unravel_index(np.arange(grid.size), cells), axis=1).astype(np.int32); "
              "to = idx[:, None, :] + moves[None].astype(np.int32); top = np.array(cells, dtype=np.int32) - 1; "
              "inside = np.all((to >= 0) & (to <= top), axis=2); to = np.clip(to, 0, top).astype(np.int32); "
              "tr = Transitions(np.maximum(to - 1, 0).astype(np.int32), np.minimum(to + 1, top).astype(np.int32), inside); del idx, to; "
              "safe = np.random.default_rng(0).random(grid.size) >= 0.05; pre(grid, safe, tr); t1 = time.perf_counter(); "
              "win = safety(grid, np.broadcast_to(safe, (steps + 1, grid.size)), tr, steps); t2 = time.perf_counter(); "
              "print(f'__GRID__ {t1 - t0:.2f} {t2 - t1:.2f} {grid.size * len(moves)} {int(win[0].sum())}')")


def grid_games(timeout: float) -> list[dict]:
    """The rows of the planner's fixed points: build and fixed point times, peak memory (:data:`GRID_GAMES`)."""
    out = []
    for label, cells, reach, steps in (("2-D, 200 x 200 cells, 25 inputs, 500 steps", "200x200", 2, 500),
                                        ("3-D, 10^6 cells, 27 inputs, 20 steps", "100x100x100", 1, 20)):
        wall, mem, text, rc = run_child([sys.executable, "-c", GRID_GAMES, cells, str(reach), str(steps)], timeout)
        line = [t for t in text.splitlines() if t.startswith("__GRID__")]
        build, fixed, count, kept = (float(x) for x in line[-1].split()[1:]) if line else (float("nan"),) * 4
        out.append({"work": f"grid games {label}", "stage": fixed, "wall": wall, "mem": mem, "rc": rc,
                    "target": "Dionysos: 11.8 million transitions built in about 4 s (3-state vehicle)",
                    "note": f"{count:.3g} transitions built in {build:.2f} s; safety kernel {kept:.0f} cells"})
        print(f"  measured {out[-1]['work']}: {fixed:.2f} s ({wall:.1f} s wall)", file=sys.stderr, flush=True)
    return out


#: Where synthesize's time goes: the plan (the EPS search, one abstraction run per tolerance) and the plant's run.
TASK_SPLIT = ("import sys, time; from ashc_cli.problem.spec import load_spec; from ashc_cli.design.pipeline import DESIGN, run, design_model; "
              "from ashc_cli.design import task_plan; from ashc_cli.closedloop.terms import DesignTerms; "
              "spec = load_spec(sys.argv[2]); arts = run(spec, sys.argv[1], DESIGN); model = design_model(spec, arts); "
              "plant = DesignTerms(model, arts); t0 = time.perf_counter(); plan = task_plan.plan_task(model, arts, plant=plant); "
              "t1 = time.perf_counter(); task_plan.task_run(model, plant, arts, plan); t2 = time.perf_counter(); "
              "print(f'plan {t1 - t0:.1f} s ({len(plan.tried)} tolerances on the abstraction), plant run {t2 - t1:.1f} s')")


def task_split(folder: Path, spec: str, timeout: float, env: dict) -> str:
    """The plan's and the plant run's share of synthesize (:data:`TASK_SPLIT` in a fresh process)."""
    try:
        proc = subprocess.run([sys.executable, "-c", TASK_SPLIT, str(folder), spec], capture_output=True, text=True, timeout=timeout, cwd=ROOT, env=env)
    except subprocess.TimeoutExpired:
        return "split timed out"
    return proc.stdout.strip().splitlines()[-1] if proc.returncode == 0 and proc.stdout.strip() else "split failed"


#: Issue 45's tasks: the plan's time with the budget, the governor and error-aware planning, and the lower bound.
TASKS = ("specs/cuk_deadlines.yaml", "specs/hover_vehicle.yaml", "tests/specs/boost_task.yaml")


def task_rows(tmp: Path, timeout: float) -> list[dict]:
    """The rows of bench/task_times.py (a fresh process; one JSON line per task)."""
    try:
        proc = subprocess.run([sys.executable, str(ROOT / "bench" / "task_times.py"), str(tmp), *TASKS], capture_output=True, text=True,
                              timeout=timeout, cwd=ROOT)
    except subprocess.TimeoutExpired:
        return []
    return [json.loads(line) for line in proc.stdout.splitlines() if line.startswith("{")]


def print_tasks(rows: list[dict]) -> None:
    """The table of :func:`task_rows`: per task, when y is in each reach set (s, the sets in order)."""
    def cell(x):
        return x if isinstance(x, str) else " / ".join("-" if not np.isfinite(v) else f"{v:.4g}" for v in x)
    print("\n| task (issue 45): y in each reach set at (s) | deadlines | EPS | budget | governor | error-aware | lower bound |")
    print("| --- | --- | --- | --- | --- | --- | --- |")
    for r in rows:
        print(f"| {r['task']} | {cell(r['deadlines'])} | {r['eps']:.4g} | {cell(r['budget'])} | {cell(r['governor'])} | {cell(r['error_aware'])} | "
              f"{cell(r['lower_bound'])} |")
    print("(all at the error-aware plan's EPS; budget and governor: the tracking scenario's guaranteed controller aimed at each "
          "set's reference, each leg from the last set's reference; lower bound: no input certified at EPS by the comparison bound "
          "has psi in the set earlier, the sets in order)")


def example_spec(folder: Path, kind: str, stages: int, edit=None) -> Path:
    """`ashc example KIND --stages N` written to folder, optionally edited (a function of the loaded YAML)."""
    path = folder / f"{kind}_{stages}.yaml"
    subprocess.run(ASHC + ["example", kind, "--stages", str(stages), "--output", str(path)], check=True, capture_output=True, cwd=ROOT)
    if edit is not None:
        import yaml

        spec = yaml.safe_load(path.read_text())
        edit(spec)
        path.write_text(yaml.safe_dump(spec, sort_keys=False, width=140))
    return path


def certificates(tmp: Path, timeout: float) -> list[dict]:
    """The rows of issue 20: contraction certificates for networks, reactors, large and unstable plants, and the
    smallest-gain objective.  Each `ashc design` runs in a fresh process."""
    out = []

    def timed(label: str, cmd: list[str], target: str, note=None) -> dict:
        try:
            wall, mem, text, rc = run_child(cmd, timeout)
        except subprocess.TimeoutExpired:
            wall, mem, text, rc = float("nan"), float("nan"), "", -1
        row = {"work": label, "stage": wall, "wall": wall, "mem": mem, "rc": rc, "target": target, "note": note(text) if note else ""}
        out.append(row)
        print(f"  measured {label}: {wall:.1f} s, {mem:.0f} MiB", file=sys.stderr, flush=True)
        return row

    def summary_value(folder: Path, stage: str, key: str) -> float:
        proc = subprocess.run(ASHC + ["summary", str(folder), "--json"], capture_output=True, text=True, cwd=ROOT)
        try:
            return float(json.loads(proc.stdout)[stage][key])
        except (ValueError, KeyError):
            return float("nan")

    def polytope_of(folder: Path) -> str:
        proc = subprocess.run(ASHC + ["summary", str(folder), "--json"], capture_output=True, text=True, cwd=ROOT)
        try:
            return str(json.loads(proc.stdout)["stabilise"].get("polytope", "?"))
        except (ValueError, KeyError):
            return "?"

    ladder_rows = []
    for N in (5, 50, 200, 1000):
        path = example_spec(tmp, "rc_ladder", N)
        folder = tmp / f"rc{N}"
        row = timed(f"RC ladder (MORwiki), N = n = {N}, `design`", ASHC + ["design", str(path), "--out", str(folder)],
                    "N = 1000: <= 300 s, <= 4 GiB" if N == 1000 else "")
        row["note"] = f"lambda = {summary_value(folder, 'stabilise', 'lambda'):.4g} ({polytope_of(folder)})"
        ladder_rows.append((N, row["wall"]))
    good = [(n, t) for n, t in ladder_rows if np.isfinite(t)]
    if len(good) >= 2:
        slope = np.polyfit(np.log([n for n, _ in good]), np.log([t for _, t in good]), 1)[0]
        out[-1]["note"] += f"; wall time grows like N^{slope:.2f} over N = {good[0][0]}..{good[-1][0]}"
    path = example_spec(tmp, "chain", 100)
    timed("chain of 100 masses, n = 200, `design`", ASHC + ["design", str(path), "--out", str(tmp / "chain100")], "<= 60 s, <= 4 GiB")

    def ill(spec):
        spec["stabilisability"]["decay_rate"] = "maximise"
        spec["parameters"]["L"] /= 100.0
        spec["parameters"]["r"] /= 10.0
    path = example_spec(tmp, "ladder", 16, ill)
    timed("ladder n = 64, L / 100 (cond M = 100), `stabilise` maximise", ASHC + ["stabilise", str(path), "--out", str(tmp / "ill")], "<= 60 s")
    for spec, label in (("specs/cstr.yaml", "CSTR (specs/cstr.yaml) at its rate 1.2"), ("specs/inverted_pendulum.yaml", "inverted pendulum, linear_gain")):
        timed(f"{label}, `design`", ASHC + ["design", spec, "--out", str(tmp / Path(spec).stem)], "",
              note=lambda text: next((line.split(": ", 1)[1][:60] for line in text.splitlines() if line.startswith("design '")), ""))
    for N, objective in ((30, "rate"), (30, "min_gain")):
        def set_objective(spec, objective=objective):
            spec["stabilisability"]["objective"] = objective
        path = example_spec(tmp, "chain", N, set_objective)
        path = path.rename(path.with_name(f"chain_{N}_{objective}.yaml"))
        folder = tmp / f"chain{N}_{objective}"
        row = timed(f"chain n = {2 * N}, objective {objective}, `design`", ASHC + ["design", str(path), "--out", str(folder)], "")
        gain = summary_value(folder, "bound", "gain")
        fal = subprocess.run(ASHC + ["falsify", str(path), "--out", str(folder), "--runs", "400", "--json"], capture_output=True, text=True, cwd=ROOT)
        try:
            ratio = float(json.loads(fal.stdout)["max_ratio_w0_zero"])
        except (ValueError, KeyError):
            ratio = float("nan")
        row["note"] = f"G = {gain:.4g}; largest error / bound on the manifold (400 runs) = {ratio:.3g}" + (" (target >= 1/30)" if objective == "min_gain" else "")
    return out


#: The import a design needs, timed bare in a fresh process: T0, the unit of issue 44's targets.
IMPORTS = "import numpy, scipy.linalg, scipy.optimize, scipy.integrate, sympy, cvxpy, clarabel, h5py, pydantic, yaml, typer"
#: Issue 44's small nonlinear plants: spec, label, target in T0.
SMALL_PLANTS = (("specs/magnetic_levitation.yaml", "magnetic levitation (3 states, linear_gain)", 5.0),
                ("specs/inverted_pendulum.yaml", "inverted pendulum (2 states, linear_gain)", 5.0),
                ("specs/saturating_spring.yaml", "saturating spring (2 states, Jacobian terms)", 5.0))


def verdict_of(text: str) -> str:
    """The verdict on `ashc design`'s last line: "proved" or "sampled (k of 15 proved)"."""
    line = next((line for line in reversed(text.splitlines()) if line.startswith("design '")), "")
    if ": proved" in line:
        return "proved"
    if "holds on samples only (" in line:
        return "sampled (" + line.split("holds on samples only (", 1)[1].split(" conditions proved")[0] + " proved)"
    return "failed" if line else "?"


def large_plants(tmp: Path, timeout: float) -> tuple[float, list[dict]]:
    """Issue 44's rows: T0 (the bare import), the switched ladder at n = 16 ... 512 (`ashc design`, wall, peak memory,
    verdict, wall / T0, and the growth exponent), and three small nonlinear plants against 5 T0."""
    t0 = min(run_child([sys.executable, "-c", IMPORTS], timeout)[0] for _ in range(3))
    out = []

    def timed(label: str, n: int, cmd: list[str], target: str) -> dict:
        try:
            wall, mem, text, rc = run_child(cmd, timeout)
        except subprocess.TimeoutExpired:
            wall, mem, text, rc = float("nan"), float("nan"), "", -1
        row = {"work": label, "n": n, "wall": wall, "mem": mem, "rc": rc, "target": target, "verdict": verdict_of(text), "t0": wall / t0}
        out.append(row)
        print(f"  measured {label}: {wall:.1f} s = {wall / t0:.1f} T0, {mem:.0f} MiB, {row['verdict']}", file=sys.stderr, flush=True)
        return row

    for N in (4, 8, 16, 32, 64, 128):
        path = ladder_spec(tmp, N)
        timed(f"switched ladder n = {4 * N}, `design`", 4 * N, ASHC + ["design", str(path), "--out", str(tmp / f"large{N}")],
              {64: "<= 20 T0, proved", 128: "<= 60 T0, <= 2 GiB, proved"}.get(N, ""))
    good = [r for r in out if r["rc"] == 0 and np.isfinite(r["wall"])]
    if len(good) >= 2:
        slope = np.polyfit(np.log([r["n"] for r in good]), np.log([r["wall"] - t0 for r in good]), 1)[0]
        out[-1]["note"] = f"wall - T0 grows like n^{slope:.2f} over n = {good[0]['n']}..{good[-1]['n']}"
    lams = {}
    for structure in ("auto", "full"):
        def ill(spec, structure=structure):
            spec["stabilisability"].update(decay_rate="maximise", structure=structure)
            spec["parameters"]["L"] /= 100.0
            spec["parameters"]["r"] /= 10.0
        where = tmp / f"ill_spec_{structure}"
        where.mkdir(exist_ok=True)
        path = example_spec(where, "ladder", 16, ill)
        folder = tmp / f"ill_{structure}"
        row = timed(f"ill-conditioned ladder n = 64 (L / 100, r / 10), `stabilise` maximise, structure: {structure}", 0,
                    ASHC + ["stabilise", str(path), "--out", str(folder)], "<= 40 T0, lambda within 1% of the dense SDP" if structure == "auto" else "")
        proc = subprocess.run(ASHC + ["summary", str(folder), "--json"], capture_output=True, text=True, cwd=ROOT)
        try:
            lams[structure] = float(json.loads(proc.stdout)["stabilise"]["lambda"])
            row["note"], row["verdict"] = f"lambda = {lams[structure]:.8g}", "(stabilise only)"
        except (ValueError, KeyError):
            row["note"] = "?"
    if len(lams) == 2:
        out[-2]["note"] += f" ({100 * (lams['full'] - lams['auto']) / lams['full']:.2g}% below the dense SDP's bisection)"
    for spec, label, target in SMALL_PLANTS:
        timed(f"{label}, `design`", 0, ASHC + ["design", spec, "--out", str(tmp / Path(spec).stem)], f"<= {target:g} T0")
    return t0, out


#: Issue 43's rows: `ashc example ring --stages N` has 2 N + N (N - 1) / 2 distinct nonlinear terms.
RING_TERMS = {2: 5, 3: 9, 5: 20, 8: 44, 11: 77}


def terms_rows(tmp: Path, timeout: float) -> list[dict]:
    """`ashc stabilise` on the pendulum ring against its number of distinct nonlinear terms (5 ... 77): wall, peak
    memory, the route taken (the vertex argument or the norm-bound test), the rate and its evidence."""
    out = []
    for N, terms in RING_TERMS.items():
        path = tmp / f"ring_{N}.yaml"
        subprocess.run(ASHC + ["example", "ring", "--stages", str(N), "--output", str(path)], check=True, capture_output=True, cwd=ROOT)
        folder = tmp / f"ring{N}"
        try:
            wall, mem, _, rc = run_child(ASHC + ["stabilise", str(path), "--out", str(folder)], timeout)
        except subprocess.TimeoutExpired:
            wall, mem, rc = float("nan"), float("nan"), -1
        proc = subprocess.run(ASHC + ["summary", str(folder), "--json"], capture_output=True, text=True, cwd=ROOT)
        try:
            st = json.loads(proc.stdout)["stabilise"]
            route = st.get("route") or f"vertex argument ({st.get('polytope')})"
            note = f"lambda = {st['lambda']:.4g}; {route}; {'proved' if 'not proved' not in str(st.get('proof')) else 'sampled'}"
        except (ValueError, KeyError):
            note = "?"
        out.append({"work": f"ring of {N} pendulums, n = {2 * N}, {terms} terms, `stabilise`", "wall": wall, "mem": mem, "rc": rc, "note": note})
        print(f"  measured ring N = {N}: {wall:.1f} s, {mem:.0f} MiB, {note}", file=sys.stderr, flush=True)
    return out


def print_large(t0: float, rows: list[dict]) -> None:
    print(f"\n| large plants fast and proved (issue 44; T0 = bare import = {t0:.2f} s) | wall (s) | wall / T0 | peak RSS (MiB) | verdict | target | note | exit |")
    print("| --- | --- | --- | --- | --- | --- | --- | --- |")
    for r in rows:
        print(f"| {r['work']} | {r['wall']:.2f} | {r['t0']:.1f} | {r['mem']:.0f} | {r['verdict']} | {r['target']} | {r.get('note', '')} | {r['rc']} |")


def print_terms(rows: list[dict]) -> None:
    print("\n| certificates against the number of terms (issue 43) | wall (s) | peak RSS (MiB) | note | exit |")
    print("| --- | --- | --- | --- | --- |")
    for r in rows:
        print(f"| {r['work']} | {r['wall']:.2f} | {r['mem']:.0f} | {r['note']} | {r['rc']} |")


#: The paired closed-loop rows of ``--against``: label, spec, the command after ``ashc``, the stage it times.
PAIRED = (
    ("Cuk `simulate`", "specs/cuk_converter.yaml", ["simulate", "--force", "--frozen"], "simulate"),
    ("governor `simulate` (tests/specs/cuk_guaranteed.yaml)", "tests/specs/cuk_guaranteed.yaml", ["simulate", "--force", "--frozen"], "simulate"),
    ("Cuk `falsify`, 3000 runs", "specs/cuk_converter.yaml", ["falsify", "--runs", "3000", "--seed", "0", "--frozen"], "falsify"),
    ("Cuk `tradeoff --tolerances 1,2,5,10,20`", "tests/specs/cuk_guaranteed.yaml", ["tradeoff", "--tolerances", "1,2,5,10,20", "--frozen"],
     "tradeoff"),
)


def paired(tmp: Path, rev: str, pairs: int, timeout: float) -> list[dict]:
    """The closed loops of this tree (A) and of git revision ``rev`` (B), in turn, on the same design folders.

    B's package is ``git archive rev`` unpacked in ``tmp`` and put first on PYTHONPATH; both share the
    interpreter and its dependencies, and a numba cache of their own (one warm-up run each compiles)."""
    base = tmp / "base"
    base.mkdir()
    archive = subprocess.run(["git", "archive", rev, "ashc_cli"], cwd=ROOT, capture_output=True, check=True).stdout
    subprocess.run(["tar", "-x", "-C", str(base)], input=archive, check=True)
    trees = {"A": ROOT, "B": base}
    rows = []
    for label, spec, args, stage in PAIRED:
        folder = tmp / Path(spec).stem
        subprocess.run(ASHC + ["design", spec, "--out", str(folder)], check=True, capture_output=True, cwd=ROOT)
        times: dict[str, list[float]] = {"A": [], "B": []}
        for k in range(pairs + 1):                     # the first pair warms the caches and is not counted
            for name, tree in trees.items():
                env = {**os.environ, "PYTHONPATH": str(tree), "ASHC_CACHE": str(tmp / f"cache_{name}")}
                cmd = [sys.executable, "-m", "ashc_cli", args[0], spec, *args[1:], "--out", str(folder)]
                wall, _, text, rc = run_child(cmd, timeout, env)
                if k and rc == 0:
                    times[name].append(stage_time(text, stage))
        a, b = np.array(times["A"]), np.array(times["B"])
        ratio = float(np.median(a / b)) if a.size and a.size == b.size else float("nan")
        rows.append({"work": label, "A": float(np.median(a)) if a.size else float("nan"), "B": float(np.median(b)) if b.size else float("nan"),
                     "ratio": ratio, "pairs": int(min(a.size, b.size))})
        print(f"  measured {label}: {rows[-1]['A']:.2f} s against {rows[-1]['B']:.2f} s", file=sys.stderr, flush=True)
    return rows


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--stages", type=int, nargs="+", default=[1, 2, 4, 8, 16, 32])
    ap.add_argument("--timeout", type=float, default=900.0)
    ap.add_argument("--runs", type=int, default=10000, help="runs of the falsify row")
    ap.add_argument("--no-closed-loops", action="store_true", help="leave out the closed-loop table")
    ap.add_argument("--no-certificates", action="store_true", help="leave out the contraction-certificate table (issue 20)")
    ap.add_argument("--only-certificates", action="store_true", help="only the contraction-certificate table")
    ap.add_argument("--only-large", action="store_true", help="only the large-plant table (issue 44: ladder n = 16..512, small plants, in T0)")
    ap.add_argument("--only-tasks", action="store_true", help="only the task table (issue 45: budget, governor, error-aware, lower bound)")
    ap.add_argument("--against", metavar="REV", help="only the closed loops, this tree against git revision REV, paired")
    ap.add_argument("--pairs", type=int, default=5, help="counted pairs of --against (after one warm-up pair)")
    args = ap.parse_args()

    if args.against:
        with tempfile.TemporaryDirectory() as tmp:
            rows = paired(Path(tmp), args.against, args.pairs, args.timeout)
        print(f"| closed loop | this tree (s) | {args.against} (s) | ratio (median of pairs) | pairs |")
        print("| --- | --- | --- | --- | --- |")
        for r in rows:
            print(f"| {r['work']} | {r['A']:.2f} | {r['B']:.2f} | {r['ratio']:.3f} | {r['pairs']} |")
        print("(seconds: the stage's own time from its progress line, median; ratio: this tree / the revision, pair by pair)")
        return 0

    rows = []
    if args.only_tasks:
        with tempfile.TemporaryDirectory() as tmp:
            print_tasks(task_rows(Path(tmp), args.timeout))
        return 0
    if args.only_large:
        with tempfile.TemporaryDirectory() as tmp:
            print_large(*large_plants(Path(tmp), args.timeout))
            print_terms(terms_rows(Path(tmp), args.timeout))
        return 0
    if args.only_certificates:
        with tempfile.TemporaryDirectory() as tmp:
            certs = certificates(Path(tmp), args.timeout)
        print("| contraction certificates (issue 20) | wall (s) | peak RSS (MiB) | target | note | exit |")
        print("| --- | --- | --- | --- | --- | --- |")
        for r in certs:
            print(f"| {r['work']} | {r['wall']:.2f} | {r['mem']:.0f} | {r['target']} | {r['note']} | {r['rc']} |")
        return 0
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        # Cold start: `ashc --help`, and the bare import time of the dependencies a design needs.
        help_wall, *_ = run_child(ASHC + ["--help"], args.timeout)
        import_wall, _, _, _ = run_child([sys.executable, "-c", IMPORTS], args.timeout)
        rows.append(measure("Cuk (n = 4)", 4, ASHC + ["design", "specs/cuk_converter.yaml", "--out", str(tmp / "cuk")], args.timeout))
        cuk_wall = rows[0]["total"]
        for N in args.stages:
            spec = tmp / f"ladder_{N}.yaml"
            subprocess.run(ASHC + ["example", "ladder", "--stages", str(N), "--output", str(spec)], check=True, capture_output=True, cwd=ROOT)
            rows.append(measure(f"ladder N = {N}", 4 * N, ASHC + ["design", str(spec), "--out", str(tmp / f"l{N}")], args.timeout))
            print(f"  measured ladder N = {N} (n = {4 * N}): {rows[-1]['total']:.1f} s", file=sys.stderr, flush=True)

    header = "| case | n | " + " | ".join(STAGES) + " | total (s) | peak RSS (MiB) | exit |"
    print(header)
    print("|" + " --- |" * (len(STAGES) + 5))
    for r in rows:
        cells = " | ".join(f"{r.get(s, float('nan')):.2f}" for s in STAGES)
        print(f"| {r['case']} | {r['n']} | {cells} | {r['total']:.2f} | {r['mem']:.0f} | {r['rc']} |")
    ladder = [r for r in rows if r["case"].startswith("ladder") and r["rc"] == 0 and np.isfinite(r["total"])]
    if len(ladder) >= 2:
        ns = np.log([r["n"] for r in ladder])
        slope = np.polyfit(ns, np.log([r["total"] for r in ladder]), 1)[0]
        # The total includes a fixed start-up (imports); the sum of the stage times shows the growth of the work.
        work = np.polyfit(ns, np.log([sum(r.get(s, 0.0) for s in STAGES) for r in ladder]), 1)[0]
        print(f"\ntotal time grows like n^{slope:.2f}, the sum of the stage times like n^{work:.2f}, "
              f"over n = {ladder[0]['n']}..{ladder[-1]['n']} (least squares on log-log)")
    print(f"cold start: `ashc --help` {help_wall:.2f} s; bare import of the dependencies {import_wall:.2f} s; "
          f"Cuk `ashc design` {cuk_wall:.2f} s = {cuk_wall / import_wall:.1f} x the import time (target <= 2.5 x)")
    loops = []
    if not args.no_closed_loops:
        with tempfile.TemporaryDirectory() as tmp:
            loops = closed_loops(Path(tmp), args.timeout, args.runs)
        print("\n| work | seconds | wall (s) | peak RSS (MiB) | target | note | exit |")
        print("| --- | --- | --- | --- | --- | --- | --- |")
        for r in loops:
            print(f"| {r['work']} | {r['stage']:.2f} | {r['wall']:.2f} | {r['mem']:.0f} | {r['target']} | {r['note']} | {r['rc']} |")
        print("(seconds: the stage's own time from its progress line; for the ladders the whole `ashc design`)")
    certs = []
    if not args.no_certificates:
        with tempfile.TemporaryDirectory() as tmp:
            certs = certificates(Path(tmp), args.timeout)
        print("\n| contraction certificates (issue 20) | wall (s) | peak RSS (MiB) | target | note | exit |")
        print("| --- | --- | --- | --- | --- | --- |")
        for r in certs:
            print(f"| {r['work']} | {r['wall']:.2f} | {r['mem']:.0f} | {r['target']} | {r['note']} | {r['rc']} |")
    with tempfile.TemporaryDirectory() as tmp:
        t0, large = large_plants(Path(tmp), args.timeout)
        terms = terms_rows(Path(tmp), args.timeout)
        tasks = task_rows(Path(tmp), args.timeout)
    print_large(t0, large)
    print_terms(terms)
    print_tasks(tasks)
    (ROOT / "bench" / "last.json").write_text(json.dumps({"rows": rows, "closed_loops": loops, "certificates": certs, "large": large, "t0": t0, "terms": terms,
                                                         "tasks": tasks}) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
