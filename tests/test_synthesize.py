"""Tests of ashc_cli.products.synthesize (`ashc synthesize`): the Cuk task is certified on the abstraction and met on
the plant, rtamt agrees with the stored run's robustness, a deadline no admissible v can meet is refused with the
part named."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from ashc_cli.closedloop.task_monitor import robustness
from ashc_cli.design.artefacts import read_artefact
from ashc_cli.problem.spec import Task, load_spec

from .conftest import CUK, ashc, edited
from .test_export import CC, CFLAGS, needs_cc
from .test_task_monitor import _rtamt

TASK_SPEC = Path(__file__).resolve().parent / "specs" / "cuk_task.yaml"


@pytest.fixture(scope="module")
def synthesized(tmp_path_factory):
    out = tmp_path_factory.mktemp("cuk_task")
    proc = ashc("synthesize", str(TASK_SPEC), "--out", str(out), "--json", check=True)
    return out, json.loads(proc.stdout), read_artefact(out / "synthesize.h5")


def test_the_cuk_task_is_certified_and_met_on_the_plant(synthesized):
    _, entry, art = synthesized
    v = art.values
    eps = entry["tolerance"]
    assert entry["certified_margin"] >= 0 and art.checks["task_certified"].passed
    assert entry["task"]["satisfied"] and entry["task"]["robustness"] >= 0
    # Theorem 2 in the budget mode: the plant's output stays within EPS of psi, so its robustness is at least psi's less EPS
    assert v["run/max_abs_error"] <= eps
    assert entry["task"]["robustness"] >= entry["plan_robustness"] - eps - float(v["plan_deviation"]) - float(v["sampling_margin"])
    # the budget's G is fitted to the part of V the plan keeps to (dbar over it, from theta's proved table): below the bound's
    G, G_V = float(v["gain_G"]), float(read_artefact(synthesized[0] / "bound.h5").value("gain"))
    assert entry["v_max"] == pytest.approx(eps / G, rel=1e-9) and G < G_V
    lo, hi = v["fitted_V"]
    assert np.all((np.asarray(v["plan/xi"]) >= lo) & (np.asarray(v["plan/xi"]) <= hi))
    # each reach's deepest hold window lies within its deadline, and the figure is drawn
    assert all(s <= r.by for s, r in zip(v["task/best_hold_starts"], load_spec(TASK_SPEC).task.reach))
    assert (synthesized[0] / "plots" / "synthesize.png").stat().st_size > 10_000


def test_rtamt_agrees_with_the_stored_runs_robustness(synthesized):
    _, entry, art = synthesized
    task = load_spec(TASK_SPEC).task
    t, keep = np.unique(np.asarray(art.values["run/t"]), return_index=True)
    y = np.asarray(art.values["run/y"])[:, keep]
    tenth = np.isclose(t * 10, np.round(t * 10), atol=1e-6)          # the samples on a 0.1 s grid, as rtamt's unit steps
    ts, ys = np.round(t[tenth] * 10), y[:, tenth]
    assert np.all(np.diff(ts) == 1)
    scaled = Task(horizon=task.horizon * 10, always=task.always,
                  reach=[{"set": r.set, "by": r.by * 10, "hold": r.hold * 10} for r in task.reach],
                  avoid=[{"set": a.set, "during": [a.during[0] * 10, a.during[1] * 10]} for a in task.avoid])
    assert _rtamt(scaled, ts, ys) == pytest.approx(robustness(task, t[tenth], ys).robustness, abs=1e-9)
    # and the stored number (every sample) is within the output's motion over 0.1 s of it
    assert entry["task"]["robustness"] == pytest.approx(_rtamt(scaled, ts, ys), abs=0.05)


def test_a_deadline_no_admissible_v_meets_is_refused_with_the_part(tmp_path):
    late = edited(TASK_SPEC, tmp_path, ("by: 250.0", "by: 8.0"))
    proc = ashc("synthesize", str(late), "--out", str(tmp_path / "o"))
    assert proc.returncode == 3
    line = proc.stderr.strip().splitlines()[-1]
    assert line.startswith("error: task.reach[0]: no tolerance makes the plan meet the task: at the best, EPS = "), line
    assert "reach[0] misses by" in line and not (tmp_path / "o" / "synthesize.h5").exists()


def test_a_spec_without_a_task_is_told_what_synthesize_needs(tmp_path):
    proc = ashc("synthesize", str(CUK), "--out", str(tmp_path / "o"))
    assert proc.returncode == 2
    assert proc.stderr.strip().splitlines()[-1] == ("error: task: missing; expected a task on the output "
                                                     "(docs/spec-format.md, 'task') for `ashc synthesize`")


# --- a task with a disturbance (audit finding 3): the deflation counts G_w ||w||_inf ---------------------------------

DISTURBED_TASK = """
name: disturbed_task
parameters: {a: 2.0}
concrete:
  states: [x]
  inputs: [u]
  f_bar: ["-a*x"]
  g: [["1"]]
  h: ["x"]
  input_bounds: [[-4, 4]]
  output_set: [[-1, 1]]
  disturbances: [w]
  e: [["1"]]
  disturbance_bounds: [[-W, W]]
stabilisability: {method: polytopic_lmi, decay_rate: 2.0}
abstract:
  states: [xi]
  inputs: [v]
  phi_bar: ["0"]
  l: ["a*xi"]
  domain: [[-1.5, 1.5]]
task:
  horizon: 12.0
  always: [[-1.5, 1.5]]
  reach:
    - {set: [[LO, HI]], by: 8.0, hold: 2.0}
  xi0: [0.0]
  planner: {kind: setpoint}
"""


def _task_spec(w: float | None, lo: float, hi: float) -> str:
    text = DISTURBED_TASK.replace("LO", str(lo)).replace("HI", str(hi))
    if w is None:
        return "\n".join(line for line in text.splitlines() if "disturbance" not in line and line.strip() != 'e: [["1"]]')
    return text.replace("[[-W, W]]", f"[[{-w}, {w}]]")


def _synthesized(text: str, tmp_path):
    from ashc_cli.design.pipeline import DESIGN, design_model, run
    from ashc_cli.problem.spec import parse_spec_text
    from ashc_cli.products.synthesize import synthesize

    spec = parse_spec_text(text)
    arts = run(spec, tmp_path, DESIGN)
    return spec, arts, synthesize(design_model(spec, arts), arts)


def _plan_on_the_disturbed_plant(spec, art, w: float) -> float:
    """The synthesised plan (its xi(t), v(t)) driving x' = -a x + SAT(a xi + q v) + w (q = 1 here), integrated by
    solve_ivp on its own numpy form; the task's robustness on y = x."""
    from scipy.integrate import solve_ivp

    t, xi, v = (np.asarray(art.values[k], dtype=float) for k in ("plan/t", "plan/xi", "plan/v"))

    def rhs(s, z):
        u = np.clip(2.0 * np.interp(s, t, xi[0]) + np.interp(s, t, v[0]), -4, 4)
        return [-2.0 * z[0] + u + w]

    sol = solve_ivp(rhs, (0.0, t[-1]), [xi[0, 0]], t_eval=t, rtol=1e-10, atol=1e-12, max_step=0.01)
    return robustness(spec.task, sol.t, sol.y).robustness


@pytest.mark.slow
def test_a_plan_certified_without_the_disturbance_breaks_under_it_so_the_disturbance_is_counted(tmp_path):
    from ashc_cli.errors import DesignError

    # the same plant without disturbances: a narrow set is certified, and a constant w = 0.3 breaks the plan
    spec, _, art = _synthesized(_task_spec(None, 0.1, 0.3), tmp_path / "plain")
    assert art.checks["task_certified"].passed
    assert min(_plan_on_the_disturbed_plant(spec, art, w) for w in (-0.3, 0.3)) < 0
    # with w in [-0.3, 0.3] in the spec, G_w ||w||_inf = 0.42 alone exceeds the set's half width: refused
    with pytest.raises(DesignError, match="task"):
        _synthesized(_task_spec(0.3, 0.1, 0.3), tmp_path / "disturbed")


@pytest.mark.slow
def test_a_task_certified_with_its_disturbance_holds_with_w_at_the_vertices(tmp_path):
    spec, arts, art = _synthesized(_task_spec(0.05, 0.5, 1.3), tmp_path)
    term = float(arts["bound"].values["disturbance_term"])
    assert art.checks["task_certified"].passed and art.values["tolerance"] >= term > 0
    G = float(art.values.get("gain_G", arts["bound"].values["gain"]))
    assert art.values["v_max"] == pytest.approx((art.values["tolerance"] - term) / G, rel=1e-9)
    worst = min(_plan_on_the_disturbed_plant(spec, art, w) for w in (-0.05, 0.0, 0.05))
    assert worst >= float(art.values["certified_margin"]) >= 0


@pytest.mark.slow
def test_falsify_attacks_the_task_with_the_disturbance_at_its_vertices(tmp_path, monkeypatch):
    # Audit finding 3 through `ashc falsify`: the plan certified without the disturbance (a stored copy of that rule:
    # the budget reads a bound without its disturbance term) is run with w held at each vertex of its box, and the
    # task's robustness goes negative; the plan that counts the disturbance keeps it >= 0.
    from types import SimpleNamespace

    from ashc_cli.closedloop import plan as guaranteed
    from ashc_cli.problem.spec import parse_spec_text
    from ashc_cli.products.campaign import run_falsify

    honest = guaranteed.guaranteed_plan

    def without_disturbance(tolerance, mode, W0, up, gain=None):
        values = {k: v for k, v in up["bound"].values.items() if k not in ("disturbance_term", "v_max_certified_with_w")}
        return honest(tolerance, mode, W0, {**up, "bound": SimpleNamespace(values=values)}, gain=gain)

    monkeypatch.setattr(guaranteed, "guaranteed_plan", without_disturbance)
    _, art = run_falsify(parse_spec_text(_task_spec(0.3, 0.1, 0.3)), tmp_path / "faulty", 4, 0, 2.0)
    assert art.values["task_disturbed/min_robustness"] < 0 and not art.checks["task_met_with_disturbances"].passed
    monkeypatch.undo()
    _, art = run_falsify(parse_spec_text(_task_spec(0.05, 0.5, 1.3)), tmp_path / "honest", 4, 0, 2.0)
    assert art.values["task_disturbed/min_robustness"] >= 0 and art.checks["task_met_with_disturbances"].passed
    assert art.values["task/min_robustness"] >= 0


def test_simulate_runs_the_task_scenario_with_the_synthesised_plan(tmp_path):
    # The task through `ashc simulate`: a spec with only a task has that scenario; the plan is synthesize's
    # (recomputed, deterministic), its plant run meets the task, and the headline says so.
    from ashc_cli.design.pipeline import DESIGN, design_model, run
    from ashc_cli.design.stages import simulate
    from ashc_cli.problem.spec import parse_spec_text
    from ashc_cli.products.synthesize import synthesize

    spec = parse_spec_text(_task_spec(0.05, 0.5, 1.3))
    arts = run(spec, tmp_path, list(DESIGN) + ["simulate"])
    sim, syn = arts["simulate"], synthesize(design_model(spec, arts), {k: arts[k] for k in DESIGN})
    v = sim.values
    assert sim.checks["task_met_on_the_plant"].passed and bool(v["task/satisfied"])
    assert float(v["task/tolerance"]) == pytest.approx(float(syn.values["tolerance"]), rel=1e-12)
    assert float(v["task/robustness"]) == pytest.approx(float(syn.values["task/robustness"]), abs=1e-6)
    assert "task met, robustness" in simulate.headline(sim)


def test_a_task_that_cannot_be_met_names_the_part_that_blocks_it(tmp_path):
    # Issue 39: an avoid set across the route was never named (reach[0] was blamed, with "a later deadline"), and a reach
    # set outside every output of the abstraction was told "a later deadline", which cannot help.
    from ashc_cli.errors import DesignError

    from .bad_inputs import LAG_TASK

    across = LAG_TASK.replace("  xi0: [0.0]", "  avoid:\n    - {set: [[0.2, 0.3]], during: [0.0, 12.0]}\n  xi0: [0.0]")
    with pytest.raises(DesignError, match=r"^task\.avoid\[0\]: lies across every route .* all of \[0, 8\] s in which reach\[0\] must be entered") as exc:
        _synthesized(across, tmp_path / "across")
    assert "deadline" not in exc.value.expected
    # a window that opens after the start: a plan that crossed in time could exist; the planner's route is named instead
    late = across.replace("during: [0.0, 12.0]", "during: [1.0, 12.0]")
    with pytest.raises(DesignError, match=r"^task\.avoid\[0\]: no tolerance makes the plan meet the task") as exc:
        _synthesized(late, tmp_path / "late")
    assert "straight route" in exc.value.expected and "deadline" not in exc.value.expected
    with pytest.raises(DesignError, match=r"^task\.reach\[0\]\.set: lies outside every output the abstraction can produce") as exc:
        _synthesized(LAG_TASK.replace("[[0.5, 0.9]]", "[[1.6, 1.9]]"), tmp_path / "outside")
    assert "deadline" not in exc.value.expected and "kappa(V)" in exc.value.expected
    # a set that meets kappa(V) only in part is aimed at where it does (its centre, 1.55, is off the curve)
    spec, _, art = _synthesized(LAG_TASK.replace("[[0.5, 0.9]]", "[[1.0, 2.1]]").replace("by: 8.0", "by: 9.0"), tmp_path / "part")
    assert art.checks["task_certified"].passed


@pytest.fixture(scope="module")
def simulated(synthesized):
    out = synthesized[0]
    ashc("simulate", str(TASK_SPEC), "--out", str(out), check=True)
    return out, read_artefact(out / "simulate.h5")


BOOST_TASK_SPEC = Path(__file__).resolve().parent / "specs" / "boost_task.yaml"


@pytest.fixture(scope="module")
def boost_simulated(tmp_path_factory):
    out = tmp_path_factory.mktemp("boost_task")
    ashc("simulate", str(BOOST_TASK_SPEC), "--out", str(out), check=True)
    return out, read_artefact(out / "simulate.h5")


@pytest.mark.parametrize("which", ["cuk", "boost"])
def test_rtamt_on_simulates_stored_task_run_is_its_robustness(which, request):
    # the task group of simulate.h5 (t, y, psi, xi, v) lets anyone monitor the run again: rtamt's discrete-time
    # monitor over every stored sample (time in units of the sampling step) gives simulate.task.robustness, on the
    # Cuk task and on the boost converter's
    spec_path = TASK_SPEC if which == "cuk" else BOOST_TASK_SPEC
    out, art = request.getfixturevalue("simulated" if which == "cuk" else "boost_simulated")
    assert bool(art.values["task/satisfied"]) and art.checks["task_met_on_the_plant"].passed
    v, task = art.values, load_spec(spec_path).task
    t, y = np.asarray(v["task/t"]), np.atleast_2d(np.asarray(v["task/y"]))
    assert {"task/psi", "task/xi", "task/v"} <= set(v) and np.asarray(v["task/xi"]).shape[1] == t.size
    dt = float(t[-1] - t[0]) / (t.size - 1)          # a uniform grid (checked below)
    steps = t / dt
    assert np.allclose(steps, np.round(steps), atol=1e-6) and np.all(np.diff(np.round(steps)) == 1)
    for x in (task.horizon, *(r.by for r in task.reach), *(r.hold for r in task.reach)):
        assert abs(x / dt - round(x / dt)) < 1e-9
    scaled = Task(horizon=task.horizon / dt, always=task.always,
                  reach=[{"set": r.set, "by": r.by / dt, "hold": r.hold / dt} for r in task.reach],
                  avoid=[{"set": a.set, "during": [a.during[0] / dt, a.during[1] / dt]} for a in task.avoid])
    span = float(np.ptp(np.asarray(load_spec(spec_path).concrete.output_set, dtype=float), axis=1).max())      # the output range
    assert _rtamt(scaled, np.round(steps), y) == pytest.approx(float(v["task/robustness"]), abs=1e-9 * span)


def test_check_report_and_plot_carry_the_task(simulated):
    out, art = simulated
    proc = ashc("check", str(TASK_SPEC), "--out", str(out), check=True)
    line = [s for s in proc.stdout.splitlines() if s.startswith("Task on the output")]
    assert len(line) == 1 and "not part of Problem 1's verdict" in line[0] and "met on the plant" in line[0]
    assert f"robustness {float(art.values['task/robustness']):.4g}" in line[0]
    ashc("report", str(TASK_SPEC), "--out", str(out), "--runs", "8", "--t-final", "2", check=True)
    page = (out / "report.html").read_text()
    section = page[page.index("<h2>Task on the output"):page.index("<h2>Figures")]
    eps = float(art.values["task/tolerance"])
    assert "as deflated by EPS" in section and "falsify: smallest robustness" in section
    lo, hi = load_spec(TASK_SPEC).task.reach[0].set[0]
    assert f"[{lo + eps:.5g}, {hi - eps:.5g}]" in section          # reach[0] shrunk by EPS on both sides
    assert "The task: y of the plant" in page and (out / "plots" / "task.png").stat().st_size > 10_000


def test_export_carries_the_plan_and_eval_replays_it(synthesized, tmp_path):
    # ashc export writes the plan next to the interface (synthesize.h5's: switching times, references, gain, v_max);
    # replayed with the exported abstraction on the plan's own RK4 grid it gives the plan's xi again; ashc eval plan
    # says the same as the exported functions
    out, entry, art = synthesized
    ashc("export", str(TASK_SPEC), "--out", str(out), "--lang", "python", "--output", str(tmp_path / "task_design.py"), check=True)
    space: dict = {}
    exec(compile((tmp_path / "task_design.py").read_text(), "task_design.py", "exec"), space)
    v = art.values
    switches, refs = np.asarray(v["switch_times"]), np.asarray(v["references"]).T        # stored (n_hat, reach sets)
    np.testing.assert_array_equal(space["PLAN_SWITCHES"], switches)
    for k, s in enumerate(switches):
        np.testing.assert_array_equal(space["ashc_plan_reference"](s), refs[k])
        if k:
            np.testing.assert_array_equal(space["ashc_plan_reference"](np.nextafter(s, -np.inf)), refs[k - 1])
    t, xi_plan = np.asarray(v["plan/t"]), np.atleast_2d(np.asarray(v["plan/xi"]))
    dt = t[1] - t[0]
    z, xi = xi_plan[:, 0].copy(), [xi_plan[:, 0].copy()]
    for ti in t[:-1]:
        def f(y):
            return space["ashc_abstract_rhs"](y, space["ashc_plan_controller"](ti, y))
        k1 = f(z)
        k2 = f(z + dt / 2 * k1)
        k3 = f(z + dt / 2 * k2)
        k4 = f(z + dt * k3)
        z = z + dt / 6 * (k1 + 2 * k2 + 2 * k3 + k4)
        xi.append(z.copy())
    width = float(np.ptp(xi_plan))
    assert np.max(np.abs(np.array(xi).T - xi_plan)) <= 1e-9 * max(width, 1.0)
    for at, want in (("t=170", space["ashc_plan_reference"](170.0)), ("t=170,xi=0.8", space["ashc_plan_controller"](170.0, [0.8]))):
        shown = ashc("eval", str(out), "plan", "--spec", str(TASK_SPEC), "--at", at, "--json", check=True)
        np.testing.assert_allclose(json.loads(shown.stdout)["value"], want, rtol=1e-12, atol=1e-15)


@needs_cc
def test_the_exported_c_plan_is_the_python_plan(synthesized, tmp_path):
    import ctypes
    import subprocess

    out = synthesized[0]
    ashc("export", str(TASK_SPEC), "--out", str(out), "--lang", "c", "--output", str(tmp_path / "task_design.c"), check=True)
    ashc("export", str(TASK_SPEC), "--out", str(out), "--lang", "python", "--output", str(tmp_path / "task_design.py"), check=True)
    lib = tmp_path / "task_design.so"
    proc = subprocess.run([CC, *CFLAGS, "-Wextra", "-pedantic", "-shared", "-fPIC", "-o", str(lib), str(tmp_path / "task_design.c"), "-lm"],
                          capture_output=True, text=True)
    assert proc.returncode == 0, proc.stderr
    so, space = ctypes.CDLL(str(lib)), {}
    exec(compile((tmp_path / "task_design.py").read_text(), "task_design.py", "exec"), space)
    P = ctypes.POINTER(ctypes.c_double)
    so.ashc_plan_reference.argtypes = [ctypes.c_double, P]
    so.ashc_plan_controller.argtypes = [ctypes.c_double, P, P]
    rng = np.random.default_rng(2)
    for t in (0.0, *np.asarray(read_artefact(out / "synthesize.h5").values["switch_times"]), *rng.uniform(0, 500, 20)):
        ref, v = np.empty(1), np.empty(1)
        xi = rng.uniform(0.0, 0.95, 1)
        so.ashc_plan_reference(float(t), ref.ctypes.data_as(P))
        so.ashc_plan_controller(float(t), xi.ctypes.data_as(P), v.ctypes.data_as(P))
        np.testing.assert_array_equal(ref, space["ashc_plan_reference"](t))
        np.testing.assert_allclose(v, space["ashc_plan_controller"](t, xi), rtol=1e-14, atol=1e-300)


THIN_TASK_REACHES = ("    - {set: [[0.1, 0.5]], by: 25.0, hold: 2.0}\n"
                     "    - {set: [[-0.5, -0.1]], by: 60.0, hold: 2.0}")


def _thin_task_spec() -> str:
    """Two reaches on the disturbed plant, w in [-0.06, 0.06]: the synthesised plan certifies a margin of 0.016."""
    text = _task_spec(0.06, 0.1, 0.5).replace("horizon: 12.0", "horizon: 64.0")
    return text.replace("    - {set: [[0.1, 0.5]], by: 8.0, hold: 2.0}", THIN_TASK_REACHES)


@pytest.mark.slow
def test_falsify_catches_the_plan_with_its_deflation_removed(tmp_path, monkeypatch):
    # Issue 41's planted wrong controller: the same plan, its switches waiting only for the sets as stated (EPS = 0 in
    # the plan, task_plan.plan_task(deflate=False)), on a task whose margin is thin: falsify's runs with w held at the
    # vertices of its box give a negative robustness; the synthesised plan keeps it >= 0 on the same runs.
    from ashc_cli.design import task_plan
    from ashc_cli.problem.spec import parse_spec_text
    from ashc_cli.products.campaign import run_falsify

    spec = parse_spec_text(_thin_task_spec())
    _, honest = run_falsify(spec, tmp_path, 4, 0, 2.0)
    assert honest.values["task_disturbed/min_robustness"] >= 0 and honest.values["task/min_robustness"] >= 0
    real = task_plan.plan_task

    def undeflated(model, up, *, deflate=None, plant=None):
        return real(model, up, deflate=False if deflate is None else deflate, plant=plant)

    monkeypatch.setattr(task_plan, "plan_task", undeflated)
    _, planted = run_falsify(spec, tmp_path, 4, 0, 2.0)
    assert planted.values["task_disturbed/min_robustness"] < 0 and not planted.checks["task_met_with_disturbances"].passed


@pytest.mark.slow
def test_a_dask_campaign_of_the_task_attack_runs_the_same_runs(tmp_path):
    # the same seed gives the same starts, the same search and so the same minimum with and without a cluster (a
    # local one started here; its worker reads the stored design from the folder)
    distributed = pytest.importorskip("distributed")
    from ashc_cli.design.pipeline import DESIGN, design_model, run
    from ashc_cli.problem.spec import parse_spec_text
    from ashc_cli.products.task_attack import attack_task

    spec = parse_spec_text(_task_spec(None, 0.5, 1.3))
    arts = run(spec, tmp_path, DESIGN)
    model = design_model(spec, arts)
    here = attack_task(model, arts, 16, seed=3)
    with distributed.LocalCluster(n_workers=1, threads_per_worker=1, processes=True, host="127.0.0.1", dashboard_address=None) as cluster:
        there = attack_task(model, arts, 16, seed=3, scheduler=cluster.scheduler_address, folder=tmp_path)
    assert here["task_searched"] == there["task_searched"] == 4 and here["task_runs"] == 16
    np.testing.assert_array_equal(here["task_starts"], there["task_starts"])
    np.testing.assert_array_equal(here["task_robustness"], there["task_robustness"])
    assert here["task_min_robustness"] == there["task_min_robustness"] >= 0
    # the search's runs start inside the certified region, as the drawn ones
    e = here["task_starts"] - here["task_starts"][0]
    W0 = np.einsum("ri,ij,rj->r", e, np.asarray(arts["stabilise"].value("M")), e)
    assert np.all(W0 <= here["task_start_region_W0"] * (1 + 1e-9))
