"""Tests of ashc_cli.closedloop.rk, the one Runge-Kutta engine: each tableau driven by :func:`rk.solve` is scipy's
solve_ivp (same method) step for step, its dense output is scipy's, and a terminal event is found where scipy
finds it.  The oracle is solve_ivp on the same right-hand side."""

import numpy as np
import pytest
import scipy.integrate as sint
from numba import njit

from ashc_cli.closedloop import rk

#: y' = A y + [sin(t), 0, 0]: a lightly damped oscillator with a forced, decaying third state.
A = np.array([[0.0, 1.0, 0.0], [-4.0, -0.1, 0.5], [0.0, 0.0, -0.7]])


@njit(inline="always")
def _call(t, y, D, row, ctx):
    a = ctx[0]
    for i in range(y.size):
        s = 0.0
        for j in range(y.size):
            s += a[i, j] * y[j]
        D[row, i] = s + (np.sin(t) if i == 0 else 0.0)


@njit(inline="always")
def _event(z, ectx):
    return z[0] - ectx[0]


@njit
def _solve(tab, exponent, t0, t1, y0, t_eval, rtol, atol, level, watch, a):
    y = y0.copy()
    out = np.full((t_eval.size, y.size), np.nan)
    hit = np.full(y.size + 1, np.nan)
    status, written, nfev, steps = rk.solve(_call, (a,), _event, (level,), watch, (tab, exponent), (t0, t1), y, (t_eval, 0, t_eval.size),
                                            (rtol, np.full(y.size, atol)), out, hit)
    return status, written, nfev, steps, out, hit


def _rhs(t, y):
    return A @ y + np.array([np.sin(t), 0.0, 0.0])


CASES = [("DOP853", rk.DOP853, rk.DOP853_EXPONENT), ("RK45", rk.DP54, rk.DP54_EXPONENT)]


@pytest.mark.parametrize("method, tab, exponent", CASES, ids=[c[0] for c in CASES])
@pytest.mark.parametrize("rtol, atol", [(1e-6, 1e-9), (1e-10, 1e-12)])
def test_each_tableau_is_scipys_method_step_for_step(method, tab, exponent, rtol, atol):
    y0 = np.array([1.0, 0.0, 2.0])
    t_eval = np.linspace(0.0, 12.0, 97)
    status, written, nfev, steps, out, _ = _solve(tab, exponent, 0.0, 12.0, y0, t_eval, rtol, atol, 0.0, False, A)
    ref = sint.solve_ivp(_rhs, (0.0, 12.0), y0, method=method, t_eval=t_eval, rtol=rtol, atol=atol)
    assert status == 0 and written == t_eval.size
    assert nfev == ref.nfev                    # the same steps, accepted and rejected
    np.testing.assert_allclose(out, ref.y.T, rtol=0, atol=1e-12 * max(1.0, np.abs(ref.y).max()))


@pytest.mark.parametrize("method, tab, exponent", CASES, ids=[c[0] for c in CASES])
def test_dense_output_is_scipys(method, tab, exponent):
    """Samples between the steps come from each tableau's dense output (DOP853's 7th-order, RK45's 4th-order)."""
    y0 = np.array([0.3, -1.0, 0.5])
    t_eval = np.sort(np.random.default_rng(0).uniform(0.0, 5.0, 40))
    t_eval[-1] = 5.0
    _, _, _, _, out, _ = _solve(tab, exponent, 0.0, 5.0, y0, t_eval, 1e-4, 1e-7, 0.0, False, A)
    ref = sint.solve_ivp(_rhs, (0.0, 5.0), y0, method=method, t_eval=t_eval, rtol=1e-4, atol=1e-7)
    # Round-off only: 1e-11 against an integration error near rtol = 1e-4 (DOP853's 7th-order polynomial, evaluated
    # in scipy's order, differs from scipy's by up to 2.5e-12 here; RK45's by < 1e-13).
    np.testing.assert_allclose(out, ref.y.T, rtol=0, atol=1e-11)


def test_terminal_event_is_found_where_scipy_finds_it():
    def event(t, y):
        return y[0] - 0.25
    event.terminal, event.direction = True, -1
    y0 = np.array([1.0, 0.0, 0.0])
    t_eval = np.linspace(0.0, 10.0, 201)
    status, written, _, _, out, hit = _solve(rk.DOP853, rk.DOP853_EXPONENT, 0.0, 10.0, y0, t_eval, 1e-8, 1e-10, 0.25, True, A)
    ref = sint.solve_ivp(_rhs, (0.0, 10.0), y0, method="DOP853", t_eval=t_eval, rtol=1e-8, atol=1e-10, events=event)
    assert status == 1
    # The samples of the steps before the event's step (the m-relation keeps none of a run that left); scipy also
    # gives those of the event's step before the event.
    assert 0 < written <= ref.t.size
    np.testing.assert_allclose(out[:written], ref.y.T[:written], atol=1e-12)
    assert hit[0] == pytest.approx(ref.t_events[0][0], abs=1e-14)
    np.testing.assert_allclose(hit[1:], ref.y_events[0][0], atol=1e-13)
    assert hit[1] == pytest.approx(0.25, abs=1e-12)


def test_step_factor_bounds_and_nan():
    assert rk.step_factor.py_func(0.0, -0.2, 0.9, 0.2, 5.0) == 5.0                 # no error: the largest growth
    assert rk.step_factor.py_func(1e-30, -0.2, 0.9, 0.2, 5.0) == 5.0
    assert rk.step_factor.py_func(1e30, -0.2, 0.9, 0.2, 5.0) == 0.2
    assert rk.step_factor.py_func(float("nan"), -0.2, 0.9, 0.2, 5.0) == 0.2        # a NaN error shrinks the step
    assert rk.step_factor.py_func(1.0, -0.125, 0.9, 0.2, 10.0) == pytest.approx(0.9)


def test_tableaus_are_consistent():
    """Row sums of A are the nodes C, the weights sum to one, the error weights to zero (each pair's order
    conditions of order one)."""
    for tab in (rk.DOP853, rk.DP54):
        A_, B, C, E = tab[0], tab[1], tab[2], tab[3]
        ns = B.size
        np.testing.assert_allclose(A_[:ns, :ns].sum(axis=1), C[:ns], atol=1e-14)
        assert B.sum() == pytest.approx(1.0, abs=1e-14)
        assert E.sum() == pytest.approx(0.0, abs=1e-14)


def test_a_span_of_length_zero_gives_its_start_and_a_backward_span_fails():
    """Found by an independent attack: a zero span divided by a zero initial step, a backward one never returned."""
    y0 = np.array([1.0, 2.0, 3.0])
    status, written, nfev, steps, out, _ = _solve(rk.DOP853, rk.DOP853_EXPONENT, 3.0, 3.0, y0, np.array([3.0]), 1e-6, 1e-9, 0.0, False, A)
    assert (status, written, nfev, steps) == (0, 1, 1, 0)
    np.testing.assert_array_equal(out[0], y0)
    status, written, nfev, _, _, _ = _solve(rk.DP54, rk.DP54_EXPONENT, 3.0, 1.0, y0, np.array([1.0]), 1e-6, 1e-9, 0.0, False, A)
    assert (status, written, nfev) == (-1, 0, 0)


def test_a_blow_up_fails_instead_of_hanging():
    """y' = A y with A = 800 I overflows: the step falls below the spacing of floating-point numbers (status -1)."""
    y0 = np.array([1.0, 1.0, 1.0])
    for tab, exponent, method in ((rk.DOP853, rk.DOP853_EXPONENT, "DOP853"), (rk.DP54, rk.DP54_EXPONENT, "RK45")):
        status, *_ = _solve(tab, exponent, 0.0, 10.0, y0, np.array([10.0]), 1e-8, 1e-10, 0.0, False, 800.0 * np.eye(3))
        with np.errstate(all="ignore"):      # scipy's overflow on the way, as the engine's
            ref = sint.solve_ivp(lambda t, y: 800.0 * y + np.array([np.sin(t), 0, 0]), (0.0, 10.0), y0, method=method, rtol=1e-8, atol=1e-10)
        assert status == -1 and ref.status == -1


def test_fixed_step_is_the_textbook_rk4_bit_for_bit_and_of_order_four():
    # the task plan's step (rk.fixed_step with rk.RK4) against RK4 written out, on a nonlinear field
    def f(y):
        return np.array([y[1], -np.sin(y[0]) - 0.3 * y[1]])

    y, h = np.array([1.2, -0.4]), 0.05
    k1 = f(y)
    k2 = f(y + 0.5 * h * k1)
    k3 = f(y + 0.5 * h * k2)
    k4 = f(y + h * k3)
    assert np.array_equal(rk.fixed_step(f, y, h, k1), y + h / 6.0 * (k1 + 2 * k2 + 2 * k3 + k4))

    def error(steps):                           # y' = -y over [0, 1]
        z, dt = np.array([1.0]), 1.0 / steps
        for _ in range(steps):
            z = rk.fixed_step(lambda u: -u, z, dt, -z)
        return abs(z[0] - np.exp(-1.0))

    assert 14.0 < error(20) / error(40) < 18.0   # halving the step divides the error by 2^4


@njit(inline="always")
def _decay(t, y, K, row, ctx):
    for i in range(y.size):
        K[row, i] = -ctx[0] * y[i]


@njit
def _hold_decay(lam, h0, h_min, rtol):
    y, K, ys, y_new = np.ones(1), np.empty((rk.DP54[0].shape[0], 1)), np.empty(1), np.empty(1)
    K[0, 0] = -lam                                           # f at the hold's start, given (FSAL)
    h, accepted, rejected, forced = rk.hold(_decay, (lam,), (rk.DP54, rk.DP54_EXPONENT), (0.0, 1.0), y, h0,
                                            (h_min, 1.0, 0.9, 0.2, 5.0), (K, ys, y_new), (rtol, np.full(1, 1e-14)))
    return y[0], h, accepted, rejected, forced, K[0, 0]


def test_a_hold_reaches_its_end_to_its_tolerance_and_forces_only_at_its_least_step():
    # falsify's driver: y' = -4 y over one hold from a step too long to accept
    y, h, accepted, rejected, forced, k0 = _hold_decay(4.0, 1.0, 1.0 / 4096, 1e-8)
    assert abs(y - np.exp(-4.0)) <= 1e-8 * 10 and forced == 0 and rejected >= 1 and accepted > 1
    assert k0 == -4.0 * y                                    # K[0] holds f at the end (the next hold's first stage)
    # with a least step of a quarter hold and a tolerance no step meets, the steps are accepted by force
    y, h, accepted, rejected, forced, _ = _hold_decay(4.0, 1.0, 0.25, 1e-16)
    assert forced == accepted == 4 and h == 0.25 and np.isfinite(y)
