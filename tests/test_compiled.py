"""Tests of ashc_cli.closedloop.compiled: the tracking and m-relation closed loops and DOP853 in numba against the scipy
path of simulate.

The oracle (tests/oracle.py: solve_ivp on the numpy laws, run by ``simulate.run_tracking`` and
``simulate.run_m_relation`` in place of the compiled loops) is the reference.  The control laws are compared point by point (the same arithmetic, so to round-off); the runs
sample by sample, to what the integration tolerance and the loop's sensitivity allow (see each test); the
m-relation's terminal event by where it stops and what it reports.
"""

from __future__ import annotations

import os
import subprocess
import sys
import textwrap

import numpy as np
import pytest
import sympy as sp

pytest.importorskip("numba")

from ashc_cli.closedloop import compiled
from ashc_cli.errors import NumericalError  # noqa: E402
from ashc_cli.design.pipeline import DESIGN, design_model, run  # noqa: E402
from ashc_cli.problem.spec import load_spec  # noqa: E402
from ashc_cli.design.stages import simulate  # noqa: E402
from ashc_cli.design.stages.simulate import SAMPLE_DT, TRACKING_TOL, sample_times  # noqa: E402
from ashc_cli.design.upstream import reference_state  # noqa: E402

from .conftest import CUK, ROOT, SPECS  # noqa: E402
from .oracle import MRelationOracle, tracking_law, use_oracles  # noqa: E402

UNSTABLE = SPECS / "unstable_linear.yaml"      # feedback: linear_gain (K != 0), one input, saturate: true
BILINEAR = SPECS / "bilinear_two_input.yaml"   # two inputs, two abstract inputs (2 x 2 delta), saturate: scale


class Design:
    """A designed spec with both paths of its tracking scenario ready."""

    def __init__(self, path, out):
        self.spec = load_spec(path)
        self.out = out
        self.arts = run(self.spec, out, DESIGN)
        self.model = design_model(self.spec, self.arts)
        self.plant = simulate.DesignTerms(self.model, self.arts)
        self.loop = compiled.tracking_loop(self.model, self.arts)
        self._reference = None

    @property
    def tracking(self):
        return self.spec.simulate.tracking

    def refs(self):
        levels = [np.atleast_1d(np.asarray(level, dtype=float)) for level in self.tracking.reference_levels]
        kappa = self.arts["kappa"].expr("kappa")
        return levels, [reference_state(self.model, self.plant, level, i, kappa) for i, level in enumerate(levels)]

    def z0(self):
        tr = self.tracking
        xi0 = np.array(tr.xi0, dtype=float)
        x0 = self.plant.p_map(*xi0)[:, 0] if tr.x0 == "on_manifold" else np.array(tr.x0, dtype=float)
        e0 = self.plant.p_map(*xi0)[:, 0] - x0
        return np.r_[xi0, x0, float(e0 @ np.asarray(self.arts["stabilise"].value("M")) @ e0)]

    def segments(self, n_levels):
        """The dwell segments exactly as run_tracking's loop walks them."""
        tr = self.tracking
        out, t0, k = [], 0.0, 0
        while t0 < tr.t_final - 1e-12:
            i = min(k, n_levels - 1)
            t1 = tr.t_final if k >= n_levels - 1 else min(tr.t_final, (k + 1) * tr.dwell)
            out.append((t0, t1, sample_times(t0, t1, SAMPLE_DT), i))
            t0, k = t1, k + 1
        return out

    def compiled_run(self):
        levels, refs = self.refs()
        ctl = self.tracking.abstract_controller
        return self.loop.run(self.z0(), self.segments(len(levels)), refs, gain=ctl.gain, v_max=ctl.v_max, q_kind=self.spec.interface.q,
                             saturate=self.spec.interface.saturate, rtol=TRACKING_TOL["rtol"], atol=TRACKING_TOL["atol"]), levels

    def scipy_run(self):
        """run_tracking on the oracle (solve_ivp on the numpy laws) instead of the compiled loop."""
        if self._reference is None:
            with pytest.MonkeyPatch.context() as mp:
                use_oracles(mp, simulate)
                self._reference = simulate.run_tracking(self.model, self.plant, self.arts)[0]
            assert not self._reference["tracking/compiled"]
        return self._reference


@pytest.fixture(scope="module")
def designs(tmp_path_factory):
    cache = {}

    def get(path):
        if path not in cache:
            cache[path] = Design(path, tmp_path_factory.mktemp(path.stem))
        return cache[path]

    return get


def _scaled_diff(a, b):
    """max |a - b| over max(1, max |b|)."""
    b = np.asarray(b, dtype=float)
    return float(np.abs(np.asarray(a, dtype=float) - b).max() / max(1.0, float(np.abs(b).max())))


# --- the control law, point by point ---------------------------------------------------------------------


@pytest.mark.parametrize("path", [CUK, UNSTABLE, BILINEAR], ids=lambda p: p.stem)
@pytest.mark.parametrize("q_kind", ["least_squares", "zero"])
@pytest.mark.parametrize("saturate", [True, False, "scale"], ids=["clip", "none", "scale"])
def test_law_matches_tracking_law(designs, path, q_kind, saturate):
    d = designs(path)
    model, plant, loop = d.model, d.plant, d.loop
    ctl = d.tracking.abstract_controller
    lam, eps = float(d.arts["bound"].value("lambda")), float(d.arts["bound"].value("epsilon"))
    rng = np.random.default_rng(1)
    lo, hi = model.V[:, 0], model.V[:, 1]
    _, refs = d.refs()
    for k in range(200):
        xi = lo + (hi - lo) * rng.random(model.n_hat)
        p = plant.p_map(*xi)[:, 0]
        x = p + (0.05 * (1 + np.abs(p)) * rng.standard_normal(model.n) if k % 4 else 0.0)   # on and near the manifold
        w = float(rng.random())
        xi_ref = refs[k % len(refs)]
        v, u, dxi, dx, r = tracking_law(plant, xi, x, xi_ref, ctl.gain, ctl.v_max, q_kind, saturate)
        dw = -(lam - eps) * w + float(np.sum((plant.L.T @ r) ** 2)) / eps
        v2, u2, dz = loop.law(xi, x, xi_ref, ctl.gain, ctl.v_max, q_kind, saturate, w)
        expected = np.r_[dxi, dx, dw]
        np.testing.assert_allclose(v2, v, rtol=1e-12, atol=1e-12 * ctl.v_max)
        np.testing.assert_allclose(u2, u, rtol=1e-12, atol=1e-12 * np.abs(model.U).max())
        np.testing.assert_allclose(dz, expected, rtol=1e-11, atol=1e-11 * np.abs(expected).max())


# --- whole runs against run_tracking ----------------------------------------------------------------------


def _compare(res, ref, tol):
    assert np.array_equal(res.t, ref["tracking/t"])
    assert np.array_equal(res.reference_index, ref["tracking/reference_index"])
    for name, mine in [("xi", res.xi), ("x", res.x), ("w_comparison", res.w), ("v", res.v), ("u", res.u), ("psi", res.psi), ("y", res.y)]:
        theirs = ref[f"tracking/{name}"]
        assert mine.shape == theirs.shape, name
        assert _scaled_diff(mine, theirs) <= tol.get(name, tol["default"]), name


def test_cuk_tracking_matches_scipy(designs):
    d = designs(CUK)
    ref = d.scipy_run()
    res, levels = d.compiled_run()
    # Same steps as solve_ivp's DOP853; the samples differ by the round-off the loop amplifies (1e-9 of the
    # scale is measured; v = delta^-1 (...) is steeper: 3e-7 of v_max at the switches).
    _compare(res, ref, {"default": 1e-7, "v": 1e-6})
    err = np.linalg.norm(res.psi - res.y, axis=0).max()
    assert err == pytest.approx(4.495, rel=1e-3)
    assert err == pytest.approx(ref["tracking/max_abs_error"], rel=1e-8)
    settle = [float(np.abs(res.psi_end[j] - levels[i]).max()) for j, (*_, i) in enumerate(d.segments(len(levels)))]
    np.testing.assert_allclose(settle, ref["tracking/settle_errors"], atol=1e-9)
    # the psi the scipy path computes with its own kappa
    np.testing.assert_allclose(res.psi, d.plant.kappa(*res.xi)[:, 0, :], rtol=1e-12, atol=1e-12)


def test_bilinear_scale_tracking_matches_scipy(designs):
    # Two inputs with saturate: scale, a 2 x 2 delta (numpy's pinv in numba), phi_bar = -xi.
    d = designs(BILINEAR)
    ref = d.scipy_run()
    res, _ = d.compiled_run()
    _compare(res, ref, {"default": 1e-8})
    assert np.linalg.norm(res.psi - res.y, axis=0).max() == pytest.approx(ref["tracking/max_abs_error"], rel=1e-8)
    assert res.u.min() >= -1 - 1e-12 and res.u.max() <= 1 + 1e-12


def test_unstable_linear_tracking_matches_scipy(designs):
    # feedback: linear_gain with K = [-1168, -484]: A + B K has eigenvalues near -2.4 and -481, so DOP853 runs
    # at its stability limit and its step sequence depends on the last bit of each stage sum (scipy against
    # itself with the stage sums added in another order: x differs by 1.5e-5, u = ... + K (x - p) by 7e-3).
    # The slow states, the outputs and the bound agree closely; x2 and u as far as that sensitivity allows.
    d = designs(UNSTABLE)
    ref = d.scipy_run()
    res, _ = d.compiled_run()
    assert d.loop.K.any()
    _compare(res, ref, {"default": 1e-6, "x": 1e-3, "u": 3e-2})
    assert np.linalg.norm(res.psi - res.y, axis=0).max() == pytest.approx(ref["tracking/max_abs_error"], rel=1e-6)


# --- failures, fallbacks, the cache -----------------------------------------------------------------------


def test_non_finite_start_is_a_numerical_error(designs):
    d = designs(CUK)
    levels, refs = d.refs()
    ctl = d.tracking.abstract_controller
    z0 = d.z0()
    z0[1] = np.nan
    with pytest.raises(NumericalError, match=r"simulate.tracking: integration failed at t = 0 s"):
        d.loop.run(z0, d.segments(len(levels))[:1], refs, gain=ctl.gain, v_max=ctl.v_max, q_kind="least_squares", saturate=True,
                   rtol=1e-9, atol=1e-9)


def test_expressions_numba_cannot_run_are_unsupported():
    x = sp.Symbol("x", real=True)
    with pytest.raises(compiled.Unsupported, match="foo"):
        compiled.emit_kernel("eval_x", "x", [x], [("h", sp.Matrix([[sp.Function("foo")(x)]]), True)], {})
    with pytest.raises(compiled.Unsupported, match="not states"):
        compiled.emit_kernel("eval_x", "x", [x], [("h", sp.Matrix([[x * sp.Symbol("k")]]), True)], {})


def test_printed_functions_run_in_numba():
    # min, max, abs, sign, sqrt, a rational power and a Piecewise, printed and compiled as the kernels are
    x = sp.Symbol("x", real=True)
    exprs = [sp.Min(x, 1), sp.Max(x, -1, 0), sp.Abs(x) + sp.sign(x), sp.sqrt(x**2 + 1), (x**2 + 1) ** sp.Rational(3, 2),
             sp.Piecewise((x, x > 0), (-x, True)), sp.exp(-x) * sp.tanh(x) + sp.atan(x)]
    src = "import math\nfrom numba import njit, types\nF1 = types.float64[::1]\nF2 = types.float64[:, ::1]\n" + compiled.emit_kernel(
        "eval_x", "x", [x], [("fb", sp.Matrix([[0]]), True), ("g", sp.Matrix([[0]]), False), ("h", sp.Matrix(exprs), True)], {})
    module = compiled.load_source(src, "ashc_test_kernel")
    f = sp.lambdify([x], exprs, "math")
    for value in (-2.5, -0.3, 0.0, 0.7, 3.0):
        h = np.empty(len(exprs))
        module.eval_x(np.array([value]), np.empty(1), np.empty((1, 1)), h)
        np.testing.assert_allclose(h, f(value), rtol=1e-15, atol=1e-15)


def test_disabled_by_environment(designs, monkeypatch):
    d = designs(CUK)
    monkeypatch.setenv("ASHC_COMPILED", "0")
    with pytest.raises(compiled.Unsupported, match="ASHC_COMPILED"):
        compiled.tracking_loop(d.model, d.arts)


def test_source_is_deterministic_and_named_by_its_hash(designs):
    d = designs(CUK)
    src = compiled.kernel_source(d.model, d.arts)
    assert src == compiled.kernel_source(d.model, d.arts)
    files = {p.name for p in compiled.cache_dir().glob("ashc_*.py")}
    assert any(name.startswith("ashc_kernels_") for name in files)
    assert d.loop.kernels.__file__.startswith(str(compiled.cache_dir()))
    # the core is the same for every design: an ordinary module of the package, not generated text
    assert d.loop.core.__name__ == "ashc_cli.closedloop.tracking_core"


def test_second_process_loads_the_cache_without_compiling(designs):
    d = designs(CUK)   # this process has compiled (or loaded) the core and the Cuk kernels
    script = textwrap.dedent(f"""
        from ashc_cli.closedloop import compiled
        from ashc_cli.design.pipeline import DESIGN, design_model, run
        from ashc_cli.problem.spec import load_spec
        spec = load_spec({str(CUK)!r})
        arts = run(spec, {str(d.out)!r}, DESIGN)
        loop = compiled.tracking_loop(design_model(spec, arts), arts)
        misses = sum(sum(f.stats.cache_misses.values()) for f in (loop.core.closed_loop, loop.core.integrate, loop.core.samples,
                                                                  loop.kernels.eval_xi, loop.kernels.eval_x))
        hits = sum(sum(f.stats.cache_hits.values()) for f in (loop.core.closed_loop, loop.core.integrate, loop.core.samples,
                                                              loop.kernels.eval_xi, loop.kernels.eval_x))
        print(misses, hits)
    """)
    proc = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, cwd=ROOT, env=os.environ.copy(), timeout=300)
    assert proc.returncode == 0, proc.stderr
    misses, hits = map(int, proc.stdout.split()[-2:])
    assert misses == 0 and hits == 5


def test_kernel_key_follows_the_expressions_and_the_parameters(designs):
    import dataclasses

    d = designs(CUK)
    key = compiled.kernel_key(d.model, d.arts)
    assert key == compiled.kernel_key(d.model, d.arts)
    assert d.loop.kernels.__name__ == f"ashc_kernels_{key}"
    values = dict(d.model.values)
    values[next(k for k in values if str(k) == "G_L")] *= 1 + 1e-15   # one bit of one parameter
    assert compiled.kernel_key(dataclasses.replace(d.model, values=values), d.arts) != key


# --- the m-relation loop against run_m_relation's solve_ivp -------------------------------------------------

BOOST = SPECS / "boost_converter.yaml"   # c(x) != 0 (nonlinear, one input), m real up to a radical's root

_M_RELATION_SERIES = ("xi", "x", "u", "v", "psi", "y")


def _m_relation_both(d, monkeypatch):
    """run_m_relation's values by the compiled loop, then by the oracle (solve_ivp)."""
    up = {k: d.arts[k] for k in simulate.UPSTREAM}
    mine, _ = simulate.run_m_relation(d.model, d.plant, up)
    with pytest.MonkeyPatch.context() as mp:
        use_oracles(mp, simulate)
        theirs, _ = simulate.run_m_relation(d.model, d.plant, up)
    assert mine["m_relation/compiled"] and not theirs["m_relation/compiled"]
    return mine, theirs


#: What an adaptive Runge-Kutta run at tolerance tol promises about its global error on these contracting
#: loops, in units of tol: it controls the local error of each step (rtol |z| + atol), and the contraction
#: keeps the sum of those from growing past a small multiple.  100 is the usual engineering rule; measured
#: against a run at rtol = atol = 1e-13 (the reference below) both paths stay within 13 tol on the Cuk
#: (numpy 2.4.6, scipy 1.17.1, numba 0.68.1), within 1 tol on the boost and the bilinear plant.
GLOBAL_ERROR_FACTOR = 100.0
#: The reference run's tolerance (two decades below the scenario's, near the floor of double precision).
REFERENCE_TOL = 1e-13


def _sensitivity(d, run, z_err):
    """First-order bounds |ds| <= |ds/dz| |dz| (per sample) of the signals derived from the state: v = b(x) + c(x) u,
    y = h(x) and psi = kappa(xi), by central differences of the plant's own compiled maps at the run's samples."""
    nh = d.model.n_hat
    xi, x, u = run["m_relation/xi"], run["m_relation/x"], run["m_relation/u"]

    def signals(xi, x):
        _, _, h_x, b, c, _ = d.plant.at_x(x)
        v = b[:, :, 0].T + np.einsum("Nij,jN->iN", c, u)
        return {"v": v, "y": h_x[:, :, 0].T, "psi": d.plant.kappa(*xi)[:, 0, :]}

    base = signals(xi, x)
    bound = {k: np.zeros_like(val) for k, val in base.items()}
    z = np.r_[xi, x]
    for j in range(z.shape[0]):
        step = 1e-6 * np.maximum(1.0, np.abs(z[j]))
        up, down = z.copy(), z.copy()
        up[j] += step
        down[j] -= step
        hi, lo = signals(up[:nh], up[nh:]), signals(down[:nh], down[nh:])
        for k in bound:
            bound[k] += np.abs(hi[k] - lo[k]) / (2 * step) * z_err[j]
    return bound


@pytest.mark.parametrize("path", [
    # The input triangle(t - 2) has a kink at t = 2 s, where DOP853 rejects steps on an error estimate near 1:
    # from there the step sequence depends on the last bit of the stage sums (compiled 40 382 right-hand-side
    # calls, scipy 40 247), and the two runs differ by what each integration's own error allows, not by round-off.
    CUK,
    BOOST,       # c(x) != 0 (nonlinear, one input), smooth input: the same steps as solve_ivp
    BILINEAR,    # two inputs, a 2 x 2 c(x), m_hat = 2
], ids=lambda p: getattr(p, "stem", None))
def test_m_relation_matches_scipy(designs, monkeypatch, path):
    # Both runs are held to what the integrations promise: each state within GLOBAL_ERROR_FACTOR x tol of a run
    # at REFERENCE_TOL (so the two within twice that of each other), and each derived signal within what its
    # sensitivity to the state carries of the state's actual error (twice the first-order bound, plus round-off).
    d = designs(path)
    mine, theirs = _m_relation_both(d, monkeypatch)
    tol = dict(simulate.M_RELATION_TOL)
    use_oracles(monkeypatch, simulate)
    monkeypatch.setitem(simulate.M_RELATION_TOL, "rtol", REFERENCE_TOL)
    monkeypatch.setitem(simulate.M_RELATION_TOL, "atol", REFERENCE_TOL)
    ref, _ = simulate.run_m_relation(d.model, d.plant, {k: d.arts[k] for k in simulate.UPSTREAM})
    promise = GLOBAL_ERROR_FACTOR * max(tol["rtol"], tol["atol"])
    for result in (mine, theirs):
        assert np.array_equal(result["m_relation/t"], ref["m_relation/t"])
        assert np.array_equal(result["m_relation/xi0"], ref["m_relation/xi0"])
        for name in ("xi", "x"):
            a, b = result[f"m_relation/{name}"], ref[f"m_relation/{name}"]
            assert a.shape == b.shape, name
            assert _scaled_diff(a, b) <= promise, name
        z_err = np.abs(np.r_[result["m_relation/xi"], result["m_relation/x"]] - np.r_[ref["m_relation/xi"], ref["m_relation/x"]])
        bound = _sensitivity(d, ref, z_err)
        np.testing.assert_array_equal(result["m_relation/u"], ref["m_relation/u"])   # u(t) at the same sample times
        for name, first_order in bound.items():
            a, b = result[f"m_relation/{name}"], ref[f"m_relation/{name}"]
            floor = 1e-12 * max(1.0, float(np.abs(b).max()))
            excess = np.abs(a - b) - (2.0 * first_order + floor)
            assert excess.max() <= 0, f"{name}: {excess.max():.3g} beyond what the state's error carries"
    # psi - y and m(x) - xi are the integration's own error: both runs keep them as small as the promise
    scale = max(1.0, float(np.abs(ref["m_relation/y"]).max()))
    for result in (mine, theirs):
        for name in ("max_abs_error", "invariance_residual"):
            assert abs(result[f"m_relation/{name}"] - ref[f"m_relation/{name}"]) <= promise * scale, name
    assert mine["m_relation/max_abs_error"] < simulate.M_RELATION_TOL_ABS


def test_boost_m_relation_takes_solve_ivps_steps(designs):
    # The loop on its own against solve_ivp on the same right-hand side, same tolerances: the same calls.
    import scipy.integrate as sint
    from ashc_cli.problem.expr import parse_expression
    from ashc_cli.problem.model import TIME, compile_flat

    d = designs(BOOST)
    mr, model, plant = d.spec.simulate.m_relation, d.model, d.plant
    u = sp.Matrix([parse_expression(mr.u, {**model.params, "t": TIME}, "u", signal=True)])
    loop = compiled.m_relation_loop(model, d.arts, u)
    u_of_t = compile_flat(list(u), [TIME], model.values)
    nh = model.n_hat
    x0 = np.array(mr.x0, dtype=float)
    z0 = np.r_[plant.h_m(x0)[1][:, 0], x0]

    def rhs(t, z):
        uu = np.array(u_of_t(t), dtype=float)
        phi, delta, *_ = plant.at_xi(z[:nh])
        f_bar, g, _, b, c, _ = plant.at_x(z[nh:])
        return np.r_[phi[:, 0] + delta @ (b[:, 0] + c @ uu), f_bar[:, 0] + g @ uu]

    t_eval = np.linspace(0.0, 2.0, 2001)
    tol = simulate.M_RELATION_TOL
    res = loop.run(z0, (0.0, 2.0), t_eval, edges=None, rtol=tol["rtol"], atol=tol["atol"])
    sol = sint.solve_ivp(rhs, (0.0, 2.0), z0, t_eval=t_eval, **tol)
    assert res.left is None and res.nfev == sol.nfev
    assert _scaled_diff(np.r_[res.xi, res.x], sol.y) <= 1e-13
    # a run shorter than one sample period (t_final = 0.4 ms: the only sample is t = 0), as solve_ivp runs it
    short = loop.run(z0, (0.0, 4e-4), np.array([0.0]), edges=None, rtol=tol["rtol"], atol=tol["atol"])
    ref = sint.solve_ivp(rhs, (0.0, 4e-4), z0, t_eval=np.array([0.0]), **tol)
    assert short.nfev == ref.nfev > 2 and np.array_equal(short.t, ref.t) and np.array_equal(np.r_[short.xi, short.x], ref.y)
    # the right-hand side point by point, u(t) at the kink-free signal's samples
    dz, v, uu = np.empty(z0.size), np.empty(model.m_hat), np.empty(model.m)
    for k in range(0, t_eval.size, 97):
        z = np.ascontiguousarray(sol.y[:, k])
        loop.core.link_loop(loop.kernels.eval_xi, loop.kernels.eval_x, loop.link.eval_link, loop.link.eval_u, loop.dims, t_eval[k], z, v, uu, dz)
        np.testing.assert_allclose(dz, rhs(t_eval[k], z), rtol=1e-14, atol=1e-14)


def _leaving_cuk(tmp_path, domain="[[0, 0.95]]"):
    """The Cuk spec's m-relation scenario alone, driven (u = 0.95 from x = 0) below kappa(V) at t = 0.78 s."""
    from ashc_cli.problem.spec import parse_spec_text

    text = CUK.read_text()
    text = text[:text.index("  tracking:")] + text[text.index("  m_relation:"):]
    for old, new in (("x0: [10.3256, 2.0561, -4.9785, -6.9732]", "x0: [0, 0, 0, 0]"),
                     ('u: "0.3*triangle(t - 2) + 0.1*sin(2*pi*(t - 2)) + 0.45"', 'u: "0.95"'), ("domain: [[0, 0.95]]", f"domain: {domain}")):
        assert old in text
        text = text.replace(old, new)
    spec = parse_spec_text(text)
    arts = run(spec, tmp_path, DESIGN)
    model = design_model(spec, arts)
    return model, simulate.DesignTerms(model, arts), {k: arts[k] for k in simulate.UPSTREAM}


@pytest.mark.parametrize("domain", ["[[0, 0.95]]", "auto"])
def test_leaving_the_certified_set_stops_both_paths_at_the_same_point(tmp_path, monkeypatch, domain):
    # The terminal event (y = h(x) crosses the end of inverse.m_domain, direction -1): solve_ivp finds the
    # time with brentq on the dense output, the compiled loop with the same root finder on its own.
    from ashc_cli.errors import DesignError

    model, plant, up = _leaving_cuk(tmp_path, domain)
    seen = {}
    run_loop, run_oracle = compiled.MRelationLoop.run, MRelationOracle.run

    def spy(which, method):
        def run(self, *args, **kwargs):
            res = method(self, *args, **kwargs)
            seen[which] = res.left
            return res
        return run

    monkeypatch.setattr(compiled.MRelationLoop, "run", spy("compiled", run_loop))
    monkeypatch.setattr(MRelationOracle, "run", spy("scipy", run_oracle))
    messages = []
    for oracle in (False, True):
        if oracle:
            use_oracles(monkeypatch, simulate)
        with pytest.raises(DesignError, match=r"simulate\.m_relation: at t = 0\.(78|79)\d* s the output y = -126\.\d+ leaves kappa\(V\)") as info:
            simulate.run_m_relation(model, plant, up)
        messages.append(str(info.value))
    assert messages[0] == messages[1]
    (t_c, z_c), (t_s, z_s) = seen["compiled"], seen["scipy"]
    assert abs(t_c - t_s) <= 1e-12          # measured 3e-15 s
    assert _scaled_diff(z_c, z_s) <= 1e-12  # measured 3e-13 of the scale


def test_signal_functions_match_the_spec_functions():
    # triangle, square and step as the printer writes them for numba, against the numpy functions the scipy
    # path evaluates (expr.NUMERIC_MODULES), at the kinks, the jumps and far out.
    from ashc_cli.problem.expr import square, step, triangle
    from ashc_cli.problem.model import TIME, compile_flat

    t = TIME
    exprs = [0.3 * triangle(t - 2) + 0.1 * sp.sin(2 * sp.pi * (t - 2)) + 0.45, square(3 * t), step(t - 1), triangle(t) * step(-t)]
    src = "\n".join(["import math", "import numpy as np", "from numba import njit, types", "F1 = types.float64[::1]", "F2 = types.float64[:, ::1]",
                     compiled.SIGNAL_IMPORT, compiled.emit_kernel("eval_u", "t", [t], [("u", sp.Matrix(exprs), True)], {})])
    module = compiled.load_source(src, "ashc_test_signals")
    numeric = compile_flat(exprs, [t])
    points = np.r_[np.linspace(-40.0, 40.0, 4001), 2.0, 2.0 + np.pi, 2.0 - np.pi, 1.0, 0.0, -0.0, np.pi / 3, 1e6 + 0.1]
    out = np.empty(len(exprs))
    for value in points:
        module.eval_u(np.array([value]), out)
        assert np.array_equal(out, np.array(numeric(value), dtype=float)), value


def test_m_relation_disabled_by_environment(designs, monkeypatch):
    d = designs(BOOST)
    monkeypatch.setenv("ASHC_COMPILED", "0")
    with pytest.raises(compiled.Unsupported, match="ASHC_COMPILED"):
        compiled.m_relation_loop(d.model, d.arts, sp.Matrix([[0.5]]))


def test_second_process_loads_the_m_relation_loop_without_compiling(designs):
    d = designs(CUK)   # this process has compiled (or loaded) the core and the Cuk kernels
    up = {k: d.arts[k] for k in simulate.UPSTREAM}
    simulate.run_m_relation(d.model, d.plant, up)   # and the Cuk's link module
    script = textwrap.dedent(f"""
        import numba
        from ashc_cli.closedloop import compiled
        from ashc_cli.design.pipeline import DESIGN, design_model, run
        from ashc_cli.problem.spec import load_spec
        from ashc_cli.design.stages import simulate
        spec = load_spec({str(CUK)!r})
        arts = run(spec, {str(d.out)!r}, DESIGN)
        model = design_model(spec, arts)
        values, _ = simulate.run_m_relation(model, simulate.DesignTerms(model, arts), arts)
        # the modules the run imported: the Cuk's kernels and its link module (generated), and the core
        from ashc_cli.closedloop import tracking_core
        modules = list(compiled._MODULES.values())
        print(sorted(m.__name__.split("_")[1] for m in modules))
        modules.append(tracking_core)
        fns = [f for mod in modules for f in vars(mod).values() if isinstance(f, numba.core.registry.CPUDispatcher)]
        misses = sum(sum(f.stats.cache_misses.values()) for f in fns)
        hits = sum(sum(f.stats.cache_hits.values()) for f in fns)
        print(values["m_relation/compiled"], misses, hits, sum(len(f.signatures) for f in fns))
    """)
    proc = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, cwd=ROOT, env=os.environ.copy(), timeout=300)
    assert proc.returncode == 0, proc.stderr
    names, (used, misses, hits, compiled_functions) = proc.stdout.splitlines()[-2], proc.stdout.split()[-4:]
    assert names == "['kernels', 'link']"
    # every compiled function of the three modules came from the cache (17: core 10, kernels 2, link 5)
    assert used == "True" and int(misses) == 0 and int(hits) == int(compiled_functions) == 17


def test_sums_over_L_keep_to_its_band_bit_for_bit():
    # weighted_norm2 and lt_times sum over L's band only: on a banded Cholesky factor the sums are the full
    # ones (the entries left out are exact zeros), and a band given too narrow changes them
    from ashc_cli.closedloop.interface import lt_times
    from ashc_cli.closedloop.laws import weighted_norm2
    from ashc_cli.numerics.linalg import lower_bandwidth

    rng = np.random.default_rng(11)
    n = 9
    for bw in (0, 1, 3, n - 1):
        A = np.tril(np.triu(rng.normal(size=(n, n)), -bw), bw)
        M = A @ A.T + n * np.eye(n)
        L = np.ascontiguousarray(np.linalg.cholesky(M))
        L[np.abs(L) < 1e-300] = 0.0
        assert lower_bandwidth(L) <= 2 * bw
        band = lower_bandwidth(L)
        r, X = rng.normal(size=n), rng.normal(size=(n, 2))
        full, out = np.empty((n, 2)), np.empty((n, 2))
        lt_times(L, n - 1, X, full)
        lt_times(L, band, X, out)
        assert np.array_equal(out, full) and np.allclose(full, L.T @ X, rtol=1e-14, atol=1e-14)
        assert weighted_norm2(L, band, r) == weighted_norm2(L, n - 1, r)
        assert weighted_norm2(L, band, r) == pytest.approx(float(np.sum((L.T @ r) ** 2)), rel=1e-13)
        if band > 0:
            assert weighted_norm2(L, band - 1, r) != weighted_norm2(L, band, r)
    with pytest.raises(ValueError, match="lower triangular"):
        lower_bandwidth(np.array([[1.0, 1.0], [0.0, 1.0]]))
    assert lower_bandwidth(np.eye(4)) == 0 and lower_bandwidth(np.zeros((3, 3))) == 0
