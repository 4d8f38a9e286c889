"""Tests of stage 7, the tracking and m-relation scenarios (Section V-D)."""

import numpy as np
import pytest
from hypothesis import given, settings, strategies as st

from ashc_cli.design.artefacts import read_artefact
from ashc_cli.closedloop import plan as gplan

from . import oracle as reference
from ashc_cli.design import upstream
from ashc_cli.design.stages import simulate
from ashc_cli.design.stages.simulate import SAMPLE_DT, sample_times

from .conftest import SPECS, TANH_INPUT, ashc, edited


@pytest.fixture(scope="module")
def sim(cli_run):
    return read_artefact(cli_run["out"] / "simulate.h5")


def test_m_relation_outputs_match(sim):
    # Theorem mRelatOutMatch: started on xi0 = m(x0) = 0.3677, psi = y for all t (here over 10 s).
    v = sim.values
    assert v["m_relation/xi0"][0] == pytest.approx(0.3677, abs=5e-5)
    assert v["m_relation/t"][-1] == pytest.approx(10.0)
    assert np.abs(v["m_relation/psi"] - v["m_relation/y"]).max() < 1e-6
    assert v["m_relation/max_abs_error"] < 1e-6


def test_integrators_are_recorded(sim):
    # Both scenarios say which DOP853 ran (the compiled one wherever numba is, as in this run) and at what tolerances.
    from ashc_cli.closedloop import compiled
    used = compiled.available()
    for scenario, tol in (("tracking", simulate.TRACKING_TOL), ("m_relation", simulate.M_RELATION_TOL)):
        assert bool(sim.values[f"{scenario}/compiled"]) is used
        assert sim.meta[f"{scenario}_integrator"] == {**tol, "implementation": "ashc_cli.closedloop.compiled (numba)" if used else "scipy.integrate.solve_ivp"}


def test_tracking_input_stays_in_U(sim):
    u = sim.values["tracking/u"]
    assert u.min() >= 0.0 and u.max() <= 1.0


def test_tracking_psi_settles_on_every_level(sim):
    v = sim.values
    levels = v["tracking/reference_levels"][:, 0]
    t, psi, idx = v["tracking/t"], v["tracking/psi"][0], v["tracking/reference_index"]
    for i, level in enumerate(levels):
        last = np.flatnonzero(idx == i)[-1]
        assert psi[last] == pytest.approx(level, abs=1e-3), f"level {i} at t = {t[last]}"


def test_tracking_error_below_uniform_bound(sim, cli_run):
    v = sim.values
    bound = read_artefact(cli_run["out"] / "bound.h5").values["gain"] * np.abs(v["tracking/v"]).max()
    err = np.abs(v["tracking/psi"] - v["tracking/y"]).max()
    assert err <= bound
    assert v["tracking/W0"] == pytest.approx(0.0, abs=1e-20)  # x0 = p(xi0)
    assert np.abs(v["tracking/v"]).max() == pytest.approx(60.0)  # v saturates at v_max at the switches (ERRATA item 9)


def test_controller_and_interface_law(paper_spec, paper_design):
    from ashc_cli.problem.model import build_model

    model = build_model(paper_spec)
    plant = simulate.DesignTerms(model, paper_design)
    xi, x0 = np.array([0.5]), np.array([1.0, 20.0, -1.0, -12.0])
    v, u, dxi, dx, _ = reference.tracking_law(plant, xi, x0, np.array([0.9]), 80.0, 60.0, "zero", True)
    assert v[0] == 60.0  # far from the reference: clipped at v_max
    assert u[0] == 0.5   # q = 0: u_w = l(xi) = xi
    delta = ((0.5 - 1) ** 2 + 44.7e-3 * 0.05 * 0.25) ** 2
    assert dxi[0] == pytest.approx(delta * 60.0)
    v, u, *_ = reference.tracking_law(plant, xi, x0, np.array([0.9]), 80.0, 60.0, "least_squares", True)
    assert 0.0 <= u[0] <= 1.0


def test_posterior_bound_holds_and_is_tighter_than_the_uniform_one(sim):
    # W' <= -(lambda - eps) W + |sqrt(M) r|^2 / eps integrated along the run (comparison lemma), r the run's
    # own dp/dxi delta v - g (u - l): |psi - y| <= sqrt(w(t) / alpha_h) at every sample.
    v = sim.values
    err = np.linalg.norm(v["tracking/e_y"], axis=0)
    post = v["tracking/posterior_bound"]
    span = 120.0                                       # output_set [-120, 0]
    assert np.all(err <= post + simulate.POSTERIOR_FLOOR_RTOL * span)
    assert sim.checks["tracking_error_within_posterior_bound"].passed
    assert v["tracking/posterior_bound_max"] == pytest.approx(post.max())
    # Measured on the Cuk spec: 81.8 V against the uniform 1430 V, about 17 times tighter.
    assert v["tracking/posterior_tightening"] > 10
    assert v["tracking/posterior_bound_max"] < v["tracking/uniform_bound"]





@settings(max_examples=300, deadline=None)
@given(st.floats(0.0, 50.0), st.floats(1e-6, 20.0), st.sampled_from([SAMPLE_DT, 1e-3, 0.1, 0.3]))
def test_sample_times_never_leave_the_segment(t0, length, dt):
    # solve_ivp refuses t_eval outside t_span; np.arange overshot it for dwell 0.3, t_final 1.2.
    t1 = t0 + length
    t = sample_times(t0, t1, dt)
    assert t[0] == t0 or length < 1e-12 * max(1.0, t1)
    assert t[-1] == t1
    assert np.all(t >= t0) and np.all(t <= t1) and np.all(np.diff(t) > 0)


def test_dwell_that_does_not_divide_t_final_runs(tmp_path):
    # Issue: dwell 0.3 with t_final 1.2 crashed simulate ("Values in t_eval are not within t_span").
    from ashc_cli.design.pipeline import run
    from ashc_cli.problem.spec import load_spec
    spec = edited(SPECS / "unstable_linear.yaml", tmp_path, ("t_final: 9.0", "t_final: 1.2"), ("dwell: 3.0", "dwell: 0.3"),
                  ("reference_levels: [0.5, -0.8, 0.2]", "reference_levels: [0.5, -0.8, 0.2, 0.4, -0.3]"))
    arts = run(load_spec(spec), tmp_path / "out", ("simulate",))
    t = np.asarray(arts["simulate"].values["tracking/t"])
    assert t[-1] == pytest.approx(1.2) and np.all(np.diff(t) > 0)


def test_a_failed_scenario_check_is_shown_by_simulate_and_by_check(tmp_path):
    # Issue: tracking_settled failed silently. A set-point gain far too small for the dwell cannot settle.
    from .conftest import ashc
    spec = edited(SPECS / "unstable_linear.yaml", tmp_path, ("gain: 5.0", "gain: 0.05"))
    out = tmp_path / "out"
    proc = ashc("simulate", str(spec), "--out", str(out))
    assert proc.returncode == 0, proc.stderr
    assert "FAILED (simulated): tracking_settled" in proc.stdout + proc.stderr
    proc = ashc("check", str(spec), "--out", str(out))
    assert proc.returncode == 0                                     # the design verdict is unchanged
    assert "Simulated scenarios" in proc.stdout
    assert any(line.split()[:3] == ["fail", "simulated", "tracking_settled"] for line in proc.stdout.splitlines())


# --- the guaranteed controller (issue 15, docs/guaranteed.md) -------------------------------------------------------

from ashc_cli.errors import DesignError  # noqa: E402

GUARANTEED = SPECS.parent / "tests" / "specs" / "cuk_guaranteed.yaml"


@pytest.fixture(scope="module")
def guaranteed(tmp_path_factory):
    """tests/specs/cuk_guaranteed.yaml (the Cuk spec, kind: guaranteed, tolerance 5 V, mode auto) designed and simulated."""
    from ashc_cli.design.pipeline import run
    from ashc_cli.problem.spec import load_spec
    out = tmp_path_factory.mktemp("cuk_guaranteed")
    arts = run(load_spec(GUARANTEED), out, ("simulate",))
    return arts


@pytest.mark.slow
def test_guaranteed_cuk_meets_five_volts_at_every_sample(guaranteed):
    sim_art, bound = guaranteed["simulate"], guaranteed["bound"].values
    v = sim_art.values
    assert v["tracking/guaranteed_mode"] == "governor" and v["tracking/guaranteed_mode_requested"] == "auto"
    assert v["tracking/tolerance"] == 5.0 and v["tracking/guaranteed_tolerance"] == pytest.approx(5.0, rel=1e-12)
    err = np.linalg.norm(v["tracking/e_y"], axis=0)
    assert np.all(err <= 5.0)
    assert sim_art.checks["tracking_error_within_tolerance"].passed
    assert sim_art.checks["tracking_error_within_tolerance"].evidence == "simulated"
    # Measured: 0.60 V. The uniform bound of the same run, G ||v||_inf, is 753 V: only the construction proves 5 V.
    assert err.max() < 1.0 < 5.0 < v["tracking/uniform_bound"]
    assert v["tracking/budget_v_max"] == pytest.approx(5.0 / bound["gain"], rel=1e-12)   # W0 = 0: (EPS - 0) / G
    assert v["tracking/compiled"]   # the governor runs compiled (ashc_cli/closedloop/governor.py)


def test_governor_keeps_w_below_its_level_and_works_at_it(guaranteed):
    v = guaranteed["simulate"].values
    alpha_h = guaranteed["bound"].values["alpha_h"]
    level = 5.0**2 * alpha_h
    w = v["tracking/w_comparison"]
    assert np.all(w <= level)                                         # the invariant: w(t) <= W_max for all t
    assert w.max() >= (1 - 2 * gplan.GOVERNOR_MARGIN) * level      # ... and the governor did push w to it
    assert np.all(v["tracking/governor_slack"] >= 0.0)                # its condition (G) at every sample
    s = v["tracking/governor_scale"]
    assert np.all((s >= 0.0) & (s <= 1.0)) and s.min() < 0.01 and s.max() == 1.0
    # |psi - y| <= sqrt(W / alpha_h) <= sqrt(w / alpha_h): the comparison system bounds the true W.
    assert np.all(v["tracking/W"] <= w * (1 + 1e-9) + 1e-12)
    assert guaranteed["simulate"].checks["tracking_w_below_level"].passed


def test_governor_reaches_every_level_at_least_twice_as_fast_as_the_budget(guaranteed):
    v = guaranteed["simulate"].values
    gov, bud = v["tracking/level_reached_within_tolerance_time"], v["tracking/budget_reach_time"]
    assert np.array_equal(gov, v["tracking/governor_reach_time"])
    assert np.all(np.isfinite(gov)) and np.all(np.isfinite(bud))      # every level reached, by both
    assert gov[0] == bud[0] == 0.0                                    # the start's own output
    # Measured (s): governor 16.29, 9.21, 9.66, 0.72, 4.13; budget 702.0, 662.6, 162.0, 2.82, 45.8.
    assert gov[1:].max() < 20.0 and bud[1:3].min() > 600.0
    speedup = v["tracking/governor_speedup"]
    assert np.isnan(speedup[0]) and np.all(speedup[1:] >= 2.0)       # 43.1, 71.9, 16.8, 3.9, 11.1
    assert speedup[1:] == pytest.approx(bud[1:] / gov[1:])


def _adversarial_start(paper_design, paper_spec, fraction, sign):
    """x0 off the manifold with W0 = fraction x W_max in the direction that makes |psi - y| largest for its W."""
    from ashc_cli.design.pipeline import design_model
    model = design_model(paper_spec, paper_design)
    plant = simulate.DesignTerms(model, paper_design)
    M = np.asarray(paper_design["stabilise"].value("M"))
    alpha_h = float(paper_design["bound"].value("alpha_h"))
    d = np.linalg.solve(M, model.C.T)[:, 0]             # maximises |C e|^2 / e^T M e: |psi - y| = sqrt(W0 / alpha_h)
    xi0 = np.array([0.6156])
    p0 = plant.p_map(*xi0)[:, 0]
    e = sign * d * np.sqrt(fraction * 5.0**2 * alpha_h / (d @ M @ d))
    x0 = p0 - e
    return model, plant, xi0, x0, float(e @ M @ e), alpha_h


@pytest.mark.parametrize("sign", [1.0, -1.0])
def test_governor_holds_the_tolerance_from_an_adversarial_start(paper_design, paper_spec, sign):
    # W0 = 0.98 W_max, along M^-1 C^T: the run starts with |psi - y| = sqrt(0.98) x 5 V and is asked for the farthest level.
    model, plant, xi0, x0, W0, alpha_h = _adversarial_start(paper_design, paper_spec, 0.98, sign)
    plan = gplan.guaranteed_plan(5.0, "governor", W0, paper_design)
    law = plan.law("governor", 80.0, 1, np.inf, 2.0, 1.0)
    ref = upstream.reference_state(model, plant, np.array([-80.9]), 0, paper_design["kappa"].expr("kappa"))
    segments = simulate.tracking_segments(3.0, 3.0, 1)
    res = simulate.closed_loop_run(model, plant, paper_design, law, np.r_[xi0, x0, W0], segments, [ref], simulate.tracking_loop_for(model, paper_design, law))
    err = np.abs(plant.kappa(*res["xi"])[:, 0, :] - res["y"])[0]
    assert err[0] == pytest.approx(np.sqrt(0.98) * 5.0, rel=1e-9)         # 4.95 V
    assert np.all(err <= 5.0) and np.all(res["w"] <= 5.0**2 * alpha_h)
    assert np.all(res["slack"] >= 0.0)
    assert plant.kappa(*res["xi"][:, -1:])[0, 0, 0] < -25.0       # it still moves towards -80.9 (from -19.1)
    # The same start under the unchecked set-point law (v_max 60) leaves the tolerance: the test can fail.
    free_law = gplan.Law("setpoint", 80.0, 60.0)
    free = simulate.closed_loop_run(model, plant, paper_design, free_law, np.r_[xi0, x0, W0], segments, [ref],
                                    simulate.tracking_loop_for(model, paper_design, free_law))
    assert np.abs(plant.kappa(*free["xi"])[:, 0, :] - free["y"]).max() > 5.5


def test_a_start_beyond_the_tolerance_is_refused_with_the_least_tolerance(paper_design):
    alpha_h = float(paper_design["bound"].value("alpha_h"))
    W0 = 1.2 * 5.0**2 * alpha_h                                   # sqrt(W0 / alpha_h) = 5.477 V > 5 V
    for mode in ("budget", "governor", "auto"):
        with pytest.raises(DesignError) as err:
            gplan.guaranteed_plan(5.0, mode, W0, paper_design)
        line = err.value.line()
        assert err.value.exit_code == 3 and "\n" not in line
        assert line.startswith("simulate.tracking.abstract_controller.tolerance: 5 cannot be guaranteed")
        assert f"a tolerance of at least {np.sqrt(1.2) * 5.0 * (1 + gplan.BUDGET_MARGIN):.6g}" in line
    # Just above the start's share, the budget exists and its v_max is what is left of the tolerance over G.
    plan = gplan.guaranteed_plan(6.0, "budget", W0, paper_design)
    G = float(paper_design["bound"].value("gain"))
    assert plan.budget_v_max == pytest.approx((6.0 - np.sqrt(1.2) * 5.0) / G, rel=1e-12)
    assert plan.budget_tolerance == pytest.approx(6.0, rel=1e-12)


def test_auto_takes_the_governor_only_when_it_can_run(paper_design):
    alpha_h = float(paper_design["bound"].value("alpha_h"))
    assert gplan.guaranteed_plan(5.0, "auto", 0.0, paper_design).mode == "governor"
    # W0 between the governor's level (less its margin) and EPS^2 alpha_h: only the budget certifies EPS.
    W0 = (1 - 0.5 * gplan.GOVERNOR_MARGIN) * 5.0**2 * alpha_h
    plan = gplan.guaranteed_plan(5.0, "auto", W0, paper_design)
    assert plan.mode == "budget" and plan.governor_refusal is not None and plan.budget_v_max > 0
    with pytest.raises(DesignError, match="above the level the governor keeps"):
        gplan.guaranteed_plan(5.0, "governor", W0, paper_design)


def _random_interface(rng, m, saturate):
    n = 4
    L = np.linalg.cholesky(np.cov(rng.normal(size=(n, 3 * n))) + 0.1 * np.eye(n))
    g = rng.normal(size=(n, m))
    U = np.sort(rng.uniform(-1, 1, size=(m, 2)), axis=1) + np.array([[-0.5, 0.5]])
    l = rng.uniform(U[:, 0], U[:, 1])
    feedback = np.zeros(m) if rng.random() < 0.5 else rng.normal(scale=0.3, size=m)
    qv = rng.normal(scale=3.0, size=m)
    dv = rng.normal(scale=3.0, size=n)
    return L, l, feedback, qv, dv, g, U


@pytest.mark.parametrize("saturate", [True, False, "scale"])
@pytest.mark.parametrize("m", [1, 2])
def test_governor_scale_is_admissible_and_the_largest(saturate, m):
    # Against brute force: |L^T r(s)|^2 evaluated on 20001 values of s through the actual interface.
    rng = np.random.default_rng(100 + m + 10 * ["x", True, False, "scale"].index(saturate))
    grid = np.linspace(0.0, 1.0, 20001)
    for _ in range(60):
        L, l, fb, qv, dv, g, U = _random_interface(rng, m, saturate)
        _, _, q2 = reference.interface_r(grid, L, l, fb, qv, dv, g, U, saturate)
        bound = float(rng.uniform(0.05, 1.5) * np.median(q2)) + 1e-3
        s, u, r, admissible = reference.governor_scale(L, l, fb, qv, dv, g, U, saturate, bound)
        u_s, r_s, q2_s = reference.interface_r(s, L, l, fb, qv, dv, g, U, saturate)
        assert np.allclose(u, u_s[0]) and np.allclose(r, r_s[0])
        ok = q2 <= bound
        if not admissible:                      # only when s = 0 itself is not admissible (K e clipped)
            assert s == 0.0 and not ok[0] and np.any(fb != 0)
            continue
        assert q2_s[0] <= bound                 # never an s that violates the condition
        best = grid[ok].max()
        exact = saturate != "scale" or not np.any(fb)
        # Piecewise affine: the true largest admissible s; otherwise at least the largest on the 65-point grid.
        assert s >= (best - 1e-9 if exact else grid[ok & np.isin(grid, np.linspace(0, 1, 65))].max() - 1e-12)


def test_s_zero_is_admissible_without_feedback_and_with_l_in_U():
    # K = 0 and l in U: r(0) = 0, so s = 0 meets any positive bound (docs/guaranteed.md, "When s = 0 is admissible").
    rng = np.random.default_rng(7)
    for saturate in (True, "scale", False):
        L, l, _, qv, dv, g, U = _random_interface(rng, 2, saturate)
        _, r0, q0 = reference.interface_r(0.0, L, l, np.zeros(2), qv, dv, g, U, saturate)
        assert np.all(r0 == 0.0) and q0[0] == 0.0
        s, *_, admissible = reference.governor_scale(L, l, np.zeros(2), 1e6 * qv, 1e6 * dv, g, U, saturate, 1e-12)
        assert admissible and 0.0 <= s < 1e-3


def test_reach_time_is_from_the_last_entry_into_the_band():
    t = np.arange(0.0, 10.0, 1.0)
    y = np.array([[10.0, 8.0, 4.0, 3.0, 6.0, 4.5, 4.0, 1.0, 0.5, 0.0]])
    assert simulate.reach_time(t, y, np.array([0.0]), 5.0, 0.0) == 5.0     # entered at 2, left at 4, in for good from 5
    assert simulate.reach_time(t + 20.0, y, np.array([0.0]), 5.0, 20.0) == 5.0
    assert np.isnan(simulate.reach_time(t, y[:, ::-1], np.array([0.0]), 5.0, 0.0))   # outside at the end: not reached


@pytest.mark.slow
def test_deadline_is_met_only_when_psi_sits_on_the_level_through_the_window(guaranteed):
    from ashc_cli.problem.spec import TimedLevel
    v = guaranteed["simulate"].values
    t, psi, y = v["tracking/t"], v["tracking/psi"], v["tracking/y"]
    level, seg = np.array([-80.9]), (20.0, 40.0)          # level 1, reached within 5 V after 16.3 s, psi settled after 17.7 s
    met, bound, observed, why = simulate._deadline_report(TimedLevel(level=-80.9, by=3.0, hold=2.0), 1, level, seg, t, psi, y,
                                                          5.0, 1e-4 * 120, "governor", "w <= W_max")
    assert not met and bound > 5.0 + 40.0 and observed > 5.0
    assert "later than by = 3 s: the deadline is too short for the v the governor mode allows" in why
    met, bound, observed, why = simulate._deadline_report(TimedLevel(level=-80.9, by=18.0, hold=2.0), 1, level, seg, t, psi, y,
                                                          5.0, 1e-4 * 120, "governor", "w <= W_max")
    assert met and bound == pytest.approx(5.0, abs=0.012) and observed <= 5.0


def test_deadlines_are_reported_by_simulate(tmp_path):
    # unstable_linear (feedback: linear_gain, a local bound: v_max_certified = 0.0158) in budget mode: compiled, and slow.
    from ashc_cli.design.pipeline import run
    from ashc_cli.problem.spec import load_spec
    spec = edited(SPECS / "unstable_linear.yaml", tmp_path, ("reference_levels: [0.5, -0.8, 0.2]", "reference_levels: [0.0, {level: 0.05, by: 2.0, hold: 1.0}, {level: 0.1, by: 0.5, hold: 1.0}]"),
                  ("{kind: setpoint, gain: 5.0, v_max: 2.0}", "{kind: guaranteed, tolerance: 0.3, gain: 5.0, mode: budget}"))
    arts = run(load_spec(spec), tmp_path / "out", ("simulate",))
    art, bound = arts["simulate"], arts["bound"].values
    v = art.values
    assert v["tracking/guaranteed_mode"] == "budget" and bool(v["tracking/compiled"]) is simulate.compiled.available()
    v_max = min(0.3 / bound["gain"], bound["v_max_certified"])          # W0 = 0
    assert v["tracking/budget_v_max"] == pytest.approx(v_max, rel=1e-12)
    assert np.abs(v["tracking/v"]).max() <= v_max * (1 + 1e-12)
    assert v["tracking/guaranteed_tolerance"] == pytest.approx(bound["gain"] * v_max, rel=1e-12) and v["tracking/guaranteed_tolerance"] <= 0.3
    assert art.checks["tracking_error_within_tolerance"].passed
    # psi = xi moves at |v| <= v_max (0.042 per s with the smallest-gain K of issue 19): 0.05 from 0 takes at least
    # 0.05 / v_max = 1.2 s (deadline 2 s: met), 0.1 from 0.05 at least 1.2 s too (deadline 0.5 s: missed).
    assert 0.05 / v_max < 2.0 and 0.05 / v_max > 0.5
    assert list(v["tracking/deadline_levels"]) == [1, 2] and list(v["tracking/deadline_met"]) == [True, False]
    assert art.checks["tracking_deadline_1"].passed and not art.checks["tracking_deadline_2"].passed
    assert f"the deadline is too short for the v the budget mode allows (|v| <= {v_max:.4g}" in art.checks["tracking_deadline_2"].description


def test_s_zero_inadmissible_when_the_feedback_clips_is_returned_and_flagged():
    # linear_gain with l + K e outside U: r(0) = -g (SAT(l + K e) - l - K e) != 0, so no s meets a small bound.
    L, g, U = np.eye(2), np.array([[0.0], [1.0]]), np.array([[-1.0, 1.0]])
    l, feedback = np.array([0.5]), np.array([1.0])                    # l + K e = 1.5, clipped to 1: r(0) = (0, 0.5)
    s, u, r, admissible = reference.governor_scale(L, l, feedback, np.array([1.0]), np.array([0.0, 1.0]), g, U, True, 0.2)
    assert not admissible and s == 0.0 and u[0] == 1.0 and np.allclose(r, [0.0, 0.5])
    # With room for r(0) the same point is admissible, and s is the largest that keeps |L^T r|^2 <= bound.
    s, u, r, admissible = reference.governor_scale(L, l, feedback, np.array([1.0]), np.array([0.0, 1.0]), g, U, True, 1.0)
    assert admissible and s == pytest.approx(0.5, abs=1e-12) and float(r @ r) <= 1.0   # r(s) = (0, s + 0.5), clipped u


def test_simulate_refuses_a_tolerance_the_start_cannot_meet(tmp_path):
    # The real entry point: exit 3, one line naming the tolerance, with the least tolerance that can be met.
    from .conftest import ashc
    spec = edited(SPECS / "unstable_linear.yaml", tmp_path, ("{kind: setpoint, gain: 5.0, v_max: 2.0}", "{kind: guaranteed, tolerance: 0.01, gain: 5.0}"),
                  ("x0: on_manifold", "x0: [0.01, 0.0]"))
    proc = ashc("simulate", str(spec), "--out", str(tmp_path / "out"))
    assert proc.returncode == 3
    # the numbers from the design itself: W0 = e^T M e for e = p(xi0) - x0 = (-0.01, 0)
    from ashc_cli.design.artefacts import read_artefact
    M = np.asarray(read_artefact(tmp_path / "out" / "stabilise.h5").values["M"])
    alpha_h = float(read_artefact(tmp_path / "out" / "bound.h5").values["alpha_h"])
    start = np.sqrt(1e-4 * M[0, 0] / alpha_h)
    assert start > 0.01
    line = proc.stderr.strip().splitlines()[-1]
    assert line.startswith("error: simulate.tracking.abstract_controller.tolerance: 0.01 cannot be guaranteed (budget mode): "
                           f"the start alone takes sqrt(W0 / alpha_h) = {start:.6g} of the tolerance 0.01")
    assert f"(sqrt(W0 / alpha_h) = {start:.6g} plus a margin), or a start nearer the manifold" in line


# --- issue 19: the whole bound of Theorem 2, and headlines that say the truth ---------------------------------------

def test_a_start_off_the_manifold_is_held_to_the_whole_bound(tmp_path):
    # x0 = (0.5, 0) off p(0) = (0, 0), v at most 0.01: |psi - y| starts at 0.5, far above G ||v||_inf = 0.07, but
    # inside sqrt(W0 e^(-(lambda - eps) t) / alpha_h) + G ||v||_inf, which the check now compares with.
    from ashc_cli.design.pipeline import run
    from ashc_cli.problem.spec import load_spec

    spec = edited(SPECS / "unstable_linear.yaml", tmp_path, ("x0: on_manifold", "x0: [0.5, 0.0]"), ("v_max: 2.0", "v_max: 0.01"))
    arts = run(load_spec(spec), tmp_path / "out", ("simulate",))
    sim = arts["simulate"]
    v = sim.values
    assert v["tracking/max_abs_error"] > v["tracking/uniform_bound"]           # the old check called this a failure
    assert v["tracking/inside_certified_region"]
    chk = sim.checks["tracking_error_within_bound"]
    assert chk.passed and chk.value <= 0
    bd = arts["bound"].values
    t = np.asarray(v["tracking/t"])
    whole = np.sqrt(v["tracking/W0"] * np.exp(-(bd["lambda"] - bd["epsilon"]) * t) / bd["alpha_h"]) + v["tracking/uniform_bound"]
    assert np.allclose(v["tracking/theorem_bound"], whole)
    assert np.all(np.linalg.norm(np.asarray(v["tracking/e_y"]), axis=0) <= whole)
    # ... and the line printed says so (it used to print "G ||v||_inf exceeded" beside a passing check)
    line = simulate.headline(sim)
    assert "exceeded" not in line and "Theorem 2 with W0 = " in line and "the run starts off the manifold" in line


def test_headline_prints_the_truth_when_a_bound_or_a_tolerance_is_exceeded():
    from ashc_cli.design.artefacts import Artefact, Check

    art = Artefact(stage="simulate")
    art.values.update({"tracking/t": np.zeros(2), "tracking/max_abs_error": 2.0, "tracking/uniform_bound": 1.0,
                       "tracking/inside_certified_region": True, "tracking/bound_evidence": "proved"})
    assert "2 > sqrt(W0 e^(-(lambda - eps) t) / alpha_h) + 1 (Theorem 2's bound exceeded)" in simulate.headline(art)
    art.checks["tracking_error_within_bound"] = Check(-0.1, True, "within Theorem 2's whole bound")
    art.values["tracking/W0"] = 0.3
    assert "2 <= sqrt(W0 e^(-(lambda - eps) t) / alpha_h) + 1 (Theorem 2 with W0 = 0.3" in simulate.headline(art)
    del art.checks["tracking_error_within_bound"]
    art.values.update({"tracking/max_abs_error": 0.5})
    assert "0.5 <= 1" in simulate.headline(art) and "sampled" not in simulate.headline(art)
    art.values.update({"tracking/bound_evidence": "sampled", "tracking/inside_certified_region": False})
    line = simulate.headline(art)
    assert "<= 1 (sampled)" in line and "not certified for this run" in line
    # a guaranteed controller whose own check failed
    art.values.update({"tracking/guaranteed_mode": "governor", "tracking/guaranteed_tolerance": 0.4, "tracking/level_reached_within_tolerance_time": np.zeros(1),
                       "tracking/bound_evidence": "proved", "tracking/inside_certified_region": True})
    art.checks["tracking_error_within_tolerance"] = Check(0.1, False, "max |psi - y| - EPS")
    assert "> 0.4: the guaranteed tolerance is NOT met" in simulate.headline(art)


def test_a_stopped_m_relation_keeps_the_tracking_results(tmp_path):
    # The m-relation run of this edit leaves kappa(V) (a bad_inputs case on its own, exit 3); with the tracking
    # scenario beside it, simulate.h5 keeps the tracking run and says which scenario stopped and why.
    spec = edited(SPECS / "cuk_converter.yaml", tmp_path, ("x0: [10.3256, 2.0561, -4.9785, -6.9732]", "x0: [0, 0, 0, 0]"),
                  ('u: "0.3*triangle(t - 2) + 0.1*sin(2*pi*(t - 2)) + 0.45"', 'u: "0.95"'))
    proc = ashc("simulate", str(spec), "--out", str(tmp_path / "out"))
    assert proc.returncode == 0, proc.stderr
    assert "FAILED (simulated): the m_relation scenario ran to its end (simulate.m_relation: at t = " in proc.stderr
    art = read_artefact(tmp_path / "out" / "simulate.h5")
    assert "tracking/t" in art.values and "m_relation/t" not in art.values
    assert "leaves kappa(V) = [-126.188, 0], where m is certified" in str(art.values["m_relation/failed"])
    chk = art.checks["m_relation_ran_to_the_end"]
    assert not chk.passed and chk.evidence == "simulated"
    assert all(c.passed for name, c in art.checks.items() if name.startswith("tracking"))


#: A plant written for the reference-signal tests: x1' = -x1 - x1^3 + x2, x2' = -x2 + u, y = x1.  With phi_bar = 0 the
#: manifold is the equilibria, p(xi) = (xi, xi + xi^3) with l = xi + xi^3, and kappa(xi) = xi: the reference state of
#: r is r itself, and the abstraction xi' = v runs the set-point law on its own (it does not read the plant).
CUBIC_LAG = """
name: cubic_lag
concrete:
  states: [x1, x2]
  inputs: [u]
  f_bar: ["-x1 - x1**3 + x2", "-x2"]
  g: [["0"], ["1"]]
  h: ["x1"]
  input_bounds: [[-3, 3]]
  output_set: [[-0.9, 0.9]]
  state_box: [[-1.2, 1.2], [-2.5, 2.5]]
stabilisability: {method: polytopic_lmi, decay_rate: 0.5, feedback: identity}
abstract:
  states: [xi]
  inputs: [v]
  phi_bar: ["0"]
  l: ["xi + xi**3"]
  domain: [[-1, 1]]
  delta: identity
simulate:
  tracking:
    t_final: 12.0
    xi0: [0.0]
    x0: on_manifold
    reference: "0.6*sin(0.8*t) + 0.2*square(0.25*t)"
    reference_period: 0.05
    abstract_controller: {kind: setpoint, gain: 4.0, v_max: 2.0}
"""


@pytest.fixture(scope="module")
def cubic_lag(tmp_path_factory):
    from ashc_cli.design.pipeline import run
    from ashc_cli.problem.spec import parse_spec_text
    return run(parse_spec_text(CUBIC_LAG), tmp_path_factory.mktemp("lag"), ("simulate",))["simulate"]


def test_a_reference_signal_is_sampled_held_and_tracked_like_an_independent_run(cubic_lag):
    from scipy.integrate import solve_ivp

    from ashc_cli.problem.expr import _np_square

    v = cubic_lag.values
    times = 0.05 * np.arange(240)
    r = 0.6 * np.sin(0.8 * times) + 0.2 * _np_square(0.25 * times)
    # The held levels are r(k T), and (kappa = xi) their reference states too.
    assert np.allclose(np.asarray(v["tracking/reference_levels"])[:, 0], r, atol=1e-12)
    t, xi, idx = np.asarray(v["tracking/t"]), np.asarray(v["tracking/xi"])[0], np.asarray(v["tracking/reference_index"])
    assert np.allclose(np.asarray(v["tracking/xi_ref"])[0], r[idx], atol=1e-9)
    # The abstraction on its own, integrated here: xi' = clip(4 (r(floor(t / T) T) - xi), -2, 2), segment by segment.
    xi_here, z = [], np.array([0.0])
    for k in range(240):
        mine = idx == k
        sol = solve_ivp(lambda s, q: np.clip(4.0 * (r[k] - q), -2.0, 2.0), (0.05 * k, min(12.0, 0.05 * (k + 1))), z,
                        t_eval=t[mine], rtol=1e-11, atol=1e-12)
        xi_here.append(sol.y[0])
        z = solve_ivp(lambda s, q: np.clip(4.0 * (r[k] - q), -2.0, 2.0), (0.05 * k, min(12.0, 0.05 * (k + 1))), z, rtol=1e-11, atol=1e-12).y[:, -1]
    assert np.abs(np.concatenate(xi_here) - xi).max() < 1e-6
    # The signal itself is stored at the samples, and how far psi = xi is from it is the independent run's distance.
    r_t = 0.6 * np.sin(0.8 * t) + 0.2 * _np_square(0.25 * t)
    assert np.allclose(np.asarray(v["tracking/reference_signal"])[0], r_t, atol=1e-12)
    assert v["tracking/max_reference_error"] == pytest.approx(np.abs(np.concatenate(xi_here) - r_t).max(), abs=1e-6)
    assert "tracking_settled" not in cubic_lag.checks and "tracking/settle_errors" not in v
    assert cubic_lag.checks["tracking_error_within_posterior_bound"].passed


@pytest.mark.parametrize("edit, message", [
    (("    reference_period: 0.05\n", "    reference_period: 0.05\n    reference_levels: [0.1]\n"), r"simulate\.tracking: gives both of reference_levels and reference"),
    (("    reference_period: 0.05\n", "    reference_period: 0.05\n    dwell: 1.0\n"), r"simulate\.tracking\.dwell: is given with a reference signal"),
    (('reference: "0.6*sin(0.8*t) + 0.2*square(0.25*t)"', 'reference: ["sin(t)", "cos(t)"]'), r"simulate\.tracking\.reference: has 2 entries; expected 1"),
    (("reference_period: 0.05", "reference_period: 20.0"), r"simulate\.tracking\.reference_period: 20 s is longer than the run"),
])
def test_a_reference_signal_is_validated(edit, message):
    from ashc_cli.errors import SpecError
    from ashc_cli.problem.spec import parse_spec_text
    with pytest.raises(SpecError, match=message):
        parse_spec_text(CUBIC_LAG.replace(*edit))


def test_a_reference_signal_naming_an_unknown_name_or_leaving_kappa_V_is_refused(tmp_path):
    from ashc_cli.design.pipeline import run
    from ashc_cli.errors import DesignError, SpecError
    from ashc_cli.problem.spec import parse_spec_text
    with pytest.raises(SpecError, match=r"simulate\.tracking\.reference\[0\]: .*omega"):
        run(parse_spec_text(CUBIC_LAG.replace("sin(0.8*t)", "sin(omega*t)")), tmp_path / "a", ("simulate",))
    with pytest.raises(DesignError, match=r"simulate\.tracking\.reference \(at t = 1\.\d+ s\): level \[1\.\d+"):
        run(parse_spec_text(CUBIC_LAG.replace("0.6*sin(0.8*t)", "0.9*sin(0.8*t)")), tmp_path / "b", ("simulate",))


def test_the_shipped_reference_signal_spec_follows_its_sine(tmp_path):
    # specs/cuk_sine_reference.yaml (its comment states these numbers): psi within 1 V of r(t) = -50 + 30 sin(0.5 t)
    # from t = 3 s (0.27 V measured), y within 1 V of psi there (0.80 V), the largest distance the start.
    from ashc_cli.design.pipeline import run
    from ashc_cli.problem.spec import load_spec
    v = run(load_spec(SPECS / "cuk_sine_reference.yaml"), tmp_path, ("simulate",))["simulate"].values
    t, psi, y = np.asarray(v["tracking/t"]), np.asarray(v["tracking/psi"])[0], np.asarray(v["tracking/y"])[0]
    r = -50 + 30 * np.sin(0.5 * t)
    late = t > 3.0
    assert np.abs(psi - r)[late].max() < 1.0 and np.abs(psi - y)[late].max() < 1.0
    assert v["tracking/max_reference_error"] == pytest.approx(abs(psi[0] - r[0]), rel=1e-9)


def _tanh_f(x, u):
    return np.array([-x[0] + x[1], -x[1] - x[1] ** 3 / 3 + np.tanh(u) + 0.2 * x[0]])


@pytest.fixture(scope="module")
def tanh_input(tmp_path_factory):
    from ashc_cli.design.pipeline import run
    from ashc_cli.problem.spec import parse_spec_text
    return run(parse_spec_text(TANH_INPUT), tmp_path_factory.mktemp("tanh"), ("simulate",), numeric=True)


def test_a_plant_not_input_affine_gets_p_kappa_m_of_its_equilibria(tanh_input):
    from scipy.optimize import brentq

    from ashc_cli.problem.model import build_model
    from ashc_cli.problem.spec import parse_spec_text
    model = build_model(parse_spec_text(TANH_INPUT))
    xi = np.linspace(-0.7, 0.7, 57)
    s = np.array([brentq(lambda q, z=z: 0.8 * q + q**3 / 3 - np.tanh(z), -2, 2, xtol=1e-15) for z in xi])
    P = upstream.p_function(tanh_input["manifold"], model)(xi[None])[:, 0, :]
    assert np.abs(P - s).max() < 1e-9                      # fitted to pde_tolerance 1e-10: 4.3e-11 measured
    y = np.linspace(-0.4, 0.4, 41)
    m = model.numeric(tanh_input["inverse"].expr("m"), list(model.x))(y, 0 * y)[0, 0]
    assert np.abs(m - np.arctanh(0.8 * y + y**3 / 3)).max() < 1e-9
    # Remark 4: condition (B) by Proposition 1 with q = 0; the m-relation link v = b(x, u) solves eq. (20) exactly.
    # q = 0 makes the least-squares sup the q = 0 sup on the same samples; dbar_q0 is the larger of that and its proved bound.
    bound_values = tanh_input["bound"].values
    assert tanh_input["bound"].checks["condition_B"].passed and bound_values["dbar_ls"] == bound_values["dbar_q0_sampled"] <= bound_values["dbar_q0"]
    assert tanh_input["delta"].checks["m_relation_link"].evidence == "proved"
    assert tanh_input["delta"].meta["link_form"].startswith("v = b(x, u)") and list(tanh_input["delta"].exprs["c"]) == [0]


def test_a_plant_not_input_affine_simulates_like_an_independent_integration(tanh_input):
    from scipy.integrate import solve_ivp

    v = tanh_input["simulate"].values
    # m-relation: the plant open loop under u(t) = 0.5 sin t, integrated here; psi reproduces y (Theorem 3).
    t, y = np.asarray(v["m_relation/t"]), np.asarray(v["m_relation/y"])[0]
    here = solve_ivp(lambda s, x: _tanh_f(x, 0.5 * np.sin(s)), (0, t[-1]), [0.05, -0.1], t_eval=t, rtol=1e-11, atol=1e-12).y[0]
    assert np.abs(y - here).max() < 1e-8
    assert np.abs(np.asarray(v["m_relation/psi"])[0] - y).max() < 1e-8
    # tracking: xi' = clip(2 (xi_ref - xi), +-0.15), u = l(xi) = xi (identity feedback, q = 0), x' = f(x, u).
    t, idx = np.asarray(v["tracking/t"]), np.asarray(v["tracking/reference_index"])
    xi_ref = [np.arctanh(0.8 * r + r**3 / 3) for r in (0.2, -0.25)]
    assert np.allclose(np.asarray(v["tracking/xi_ref"])[0][[0, -1]], xi_ref, atol=1e-9)
    z, xs = np.r_[0.0, 0.0, 0.0], []
    for k, (t0, t1) in enumerate([(0.0, 8.0), (8.0, 16.0)]):
        def rhs(s, q, r=xi_ref[k]):
            return np.r_[np.clip(2.0 * (r - q[0]), -0.15, 0.15), _tanh_f(q[1:], np.clip(q[0], -0.8, 0.8))]
        mine = idx == k
        sol = solve_ivp(rhs, (t0, t1), z, t_eval=t[mine], rtol=1e-11, atol=1e-12, max_step=0.05)
        xs.append(sol.y)
        z = solve_ivp(rhs, (t0, t1), z, rtol=1e-11, atol=1e-12, max_step=0.05).y[:, -1]
    here = np.concatenate(xs, axis=1)
    assert np.abs(np.asarray(v["tracking/xi"])[0] - here[0]).max() < 1e-6
    assert np.abs(np.asarray(v["tracking/x"]) - here[1:]).max() < 1e-6
    assert np.allclose(np.asarray(v["tracking/u"])[0], np.clip(here[0], -0.8, 0.8), atol=1e-6)
    assert tanh_input["simulate"].checks["tracking_error_within_bound"].passed


def test_a_plant_not_input_affine_refuses_a_linear_gain(tmp_path):
    from ashc_cli.design.pipeline import run
    from ashc_cli.errors import DesignError
    from ashc_cli.problem.spec import parse_spec_text
    text = TANH_INPUT.replace("decay_rate: maximise}", "decay_rate: maximise, feedback: linear_gain}")
    with pytest.raises(DesignError, match=r"stabilisability\.feedback: linear_gain needs an input-affine plant"):
        run(parse_spec_text(text), tmp_path, ("stabilise",))


def test_an_abstract_input_signal_drives_the_abstraction_and_the_plant_follows(tmp_path):
    # abstract_controller.kind signal: v(t) = 0.1 sin(0.5 t), so xi(t) = 0.2 (1 - cos(0.5 t)) exactly (phi_bar = 0,
    # delta = 1); the plant under u = l(xi(t)) = xi(t) is integrated here.
    from scipy.integrate import solve_ivp

    from ashc_cli.design.pipeline import run
    from ashc_cli.problem.spec import parse_spec_text
    text = TANH_INPUT.replace("    reference_levels: [0.2, -0.25]\n    dwell: 8.0\n", "").replace(
        "abstract_controller: {kind: setpoint, gain: 2.0, v_max: 0.15}", 'abstract_controller: {kind: signal, v: "0.1*sin(0.5*t)"}')
    text = text[:text.index("  m_relation:")]
    art = run(parse_spec_text(text), tmp_path, ("simulate",), numeric=True)["simulate"]
    v = art.values
    t = np.asarray(v["tracking/t"])
    assert np.abs(np.asarray(v["tracking/v"])[0] - 0.1 * np.sin(0.5 * t)).max() < 1e-12
    assert np.abs(np.asarray(v["tracking/xi"])[0] - 0.2 * (1 - np.cos(0.5 * t))).max() < 1e-8
    here = solve_ivp(lambda s, x: _tanh_f(x, 0.2 * (1 - np.cos(0.5 * s))), (0, 16.0), [0.0, 0.0], t_eval=t, rtol=1e-11, atol=1e-12).y
    assert np.abs(np.asarray(v["tracking/x"]) - here).max() < 1e-7
    assert "tracking_settled" not in art.checks and "tracking/reference_levels" not in v
    assert v["tracking/v_inf"] == pytest.approx(0.1, rel=1e-6) and art.checks["tracking_error_within_bound"].passed
    # `ashc summary` of such a run (a KeyError on tracking/settle_errors before: issue 39)
    from ashc_cli.outputs.query import summary

    assert "settle_errors" not in summary({"simulate": art})["simulate"]["tracking"]


@pytest.mark.parametrize("edit, message", [
    (("abstract_controller: {kind: setpoint, gain: 2.0, v_max: 0.15}", 'abstract_controller: {kind: signal, v: "0.1*sin(t)"}'),
     r"simulate\.tracking\.reference_levels: is given with abstract_controller\.kind: signal"),
    (("    reference_levels: [0.2, -0.25]\n    dwell: 8.0\n    abstract_controller: {kind: setpoint, gain: 2.0, v_max: 0.15}",
      '    abstract_controller: {kind: signal, v: ["sin(t)", "cos(t)"]}'), r"simulate\.tracking\.abstract_controller\.v: has 2 entries; expected 1"),
])
def test_an_abstract_input_signal_is_validated(edit, message):
    from ashc_cli.errors import SpecError
    from ashc_cli.problem.spec import parse_spec_text
    with pytest.raises(SpecError, match=message):
        parse_spec_text(TANH_INPUT.replace(*edit))


def test_a_constant_disturbance_offsets_the_plant_by_its_steady_state_within_G_w(tmp_path):
    # x' = -2 x + u + w with u = l(xi) = 2 xi and v = 0: xi stays 0 and x -> w0 / 2, so |psi - y| = 0.05 (1 - e^(-2 t))
    # for w0 = 0.1, inside Theorem 2's bound with the disturbance term G_w |w0| (tests/test_bound.py: G_w = G here).
    from ashc_cli.design.pipeline import run
    from ashc_cli.problem.spec import parse_spec_text

    from .test_bound import DISTURBED
    text = DISTURBED + """simulate:
  tracking:
    t_final: 6.0
    xi0: [0.0]
    abstract_controller: {kind: signal, v: "0"}
    disturbance: [0.1]
"""
    art = run(parse_spec_text(text), tmp_path, ("simulate",))["simulate"]
    v = art.values
    t, e = np.asarray(v["tracking/t"]), np.asarray(v["tracking/e_y"])[0]
    assert np.abs(-e - 0.05 * (1 - np.exp(-2 * t))).max() < 1e-8
    assert v["tracking/uniform_bound"] >= 0.05 and art.checks["tracking_error_within_bound"].passed
    assert art.checks["tracking_error_within_posterior_bound"].passed        # the comparison system counts e w0
    with pytest.raises(Exception, match=r"simulate\.tracking\.disturbance\[0\]: 0\.5 is outside disturbance_bounds"):
        parse_spec_text(text.replace("disturbance: [0.1]", "disturbance: [0.5]"))


@pytest.mark.slow
def test_a_guaranteed_controller_on_a_reference_signal_has_a_one_line_headline(tmp_path):
    # Audit finding 8: with a reference signal every sample is a 'level', and the headline printed the reach time of
    # each (an array of 3000 NaN, 100,141 characters).  A moving reference has no level to reach.
    from .conftest import ashc, edited

    spec = edited(SPECS / "cuk_sine_reference.yaml", tmp_path,
                  ("abstract_controller: {kind: setpoint, gain: 80.0, v_max: 60.0}",
                   "abstract_controller: {kind: guaranteed, tolerance: 5.0, gain: 80.0, mode: budget}"),
                  ("t_final: 30.0", "t_final: 3.0"))
    proc = ashc("simulate", str(spec), "--out", str(tmp_path / "o"))
    assert proc.returncode == 0, proc.stderr
    line = next(l for l in proc.stdout.splitlines() + proc.stderr.splitlines() if "tracking max|psi - y|" in l)
    assert len(line) < 400 and "nan" not in line.lower() and "following the reference signal" in line, line


def test_a_simulated_run_that_breaks_a_proved_verdict_is_reported_as_a_bug(tmp_path, capsys):
    # Audit: simulate flagged the error row of a design whose check said "proved".  A run inside the certified region
    # that breaks a guarantee of a proved design is a bug in ashc (exit 1, one line), not a result.
    import typer

    from ashc_cli.cli.stage_commands import _refuse_contradicted
    from ashc_cli.design.artefacts import Artefact, Check
    from ashc_cli.design.pipeline import DESIGN, run
    from ashc_cli.design.verdict import verdict
    from ashc_cli.problem.spec import parse_spec_text

    from .test_bound import DISTURBED

    lag = "\n".join(line for line in DISTURBED.splitlines() if "disturbance" not in line and line.strip() != 'e: [["1"]]')
    arts = run(parse_spec_text(lag), tmp_path, DESIGN)
    assert verdict(arts).proved
    sim = Artefact(stage="simulate")
    sim.values["tracking/inside_certified_region"] = True
    sim.checks["tracking_settled"] = Check(0.5, False, "the set-point controller's choice, no guarantee")
    _refuse_contradicted(arts, sim, tmp_path)                     # not a contradiction
    sim.checks["tracking_error_within_bound"] = Check(0.25, False, "max |psi - y| - bound")
    with pytest.raises(typer.Exit) as caught:
        _refuse_contradicted(arts, sim, tmp_path)
    assert caught.value.exit_code == 1
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "bug in ashc" in err[0] and "tracking_error_within_bound = 0.25" in err[0]
    sim.values["tracking/inside_certified_region"] = False        # a start outside the region claims nothing
    _refuse_contradicted(arts, sim, tmp_path)
