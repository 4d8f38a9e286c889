"""Stage 7: closed-loop simulation of the two scenarios of Section V-D.

**Tracking** (Figs. Example_BoundedIn/Out).  The abstract system xi' = phi_bar(xi) + delta(xi) v is driven by
the spec's set-point controller v = clip(delta^+(xi) (gain (xi_ref - xi) - phi_bar(xi)), -v_max, v_max),
where xi_ref is the least-norm point of V with kappa(xi_ref) = the current reference level.  The concrete
system receives the interface u_w = sat(l(xi) + q(xi, x) v) (eqs. egInterface, egInterfaceSat) with
q = 0 or the least-squares q of eq. egqLS.  The run records psi = kappa(xi), y = h(x), their error and the
uniform bound G ||v||_inf of eq. egErrorBound (valid since W(xi0, x0) = 0 when x0 = p(xi0)).

**m-relation** (Figs. Example_mRelationIn/Out).  The concrete system runs open loop under the spec's u(t);
the abstract system, started at xi0 = m(x0), receives v = b(x) + c(x) u (eq. mRelateLink).  By Theorem
mRelatOutMatch the outputs must coincide: the run records max |psi - y|.

Both integrate with DOP853 at the tolerances recorded in the artefact (meta ``tracking_integrator`` and
``m_relation_integrator``, with the implementation that ran): with a compiled closed loop (ashc_cli/compiled.py:
numba, scipy's DOP853 and solve_ivp's terminal event ported step for step; ``tracking/compiled`` and
``m_relation/compiled`` say so), and with scipy's solve_ivp, the reference, where numba is missing, an
expression has no numba form, or ASHC_COMPILED=0.
"""

from __future__ import annotations

from dataclasses import replace

import cvxpy as cp
import numpy as np
import scipy.integrate as sint
import scipy.optimize as sopt
import sympy as sp

from .. import compiled
from ..artefacts import Artefact, Check
from ..proofs import SIMULATED
from ..errors import DesignError, NumericalError
from ..expr import parse_expression
from ..grids import domain_grid
from .inverse import DOMAIN_RTOL, certified_set, format_box, outside_certified_set
from ..model import TIME, Model, apply_saturation, compile_flat, compile_terms

NAME = "simulate"
UPSTREAM = ("stabilise", "manifold", "kappa", "inverse", "delta", "bound")

TRACKING_TOL = {"method": "DOP853", "rtol": 1e-9, "atol": 1e-9}
M_RELATION_TOL = {"method": "DOP853", "rtol": 1e-11, "atol": 1e-11}
SAMPLE_DT = 1e-3
#: The measured error may exceed the a-posteriori bound by this fraction of the output span (integration error).
POSTERIOR_FLOOR_RTOL = 1e-7
#: psi must end each dwell within this fraction of the output span of its level.
SETTLE_RTOL = 1e-4
#: m-relation: outputs must match to this (V), Theorem mRelatOutMatch.
M_RELATION_TOL_ABS = 1e-6
#: The m-relation run stops when y comes this close (fraction of the certified interval) to an end where m
#: stops being real (there dm/dx blows up); at the other ends of the certified set it stops on the end.
EDGE_MARGIN = 1e-3


class _Plant:
    """The numeric terms of a design, compiled into fused functions, each on its first use.

    ``at_xi(xi)`` gives phi_bar, delta, l, dp/dxi delta and kappa at one abstract state; ``at_x(x)`` gives
    f_bar, g, h, b and c at one concrete state.  One call each per right-hand side keeps the ODE fast.
    ``h_m(x)`` gives h and m alone, for the m-relation's start and stop.  The compiled loops
    (ashc_cli.compiled) call neither at_xi nor at_x, so they are compiled only when the scipy path runs (on the
    Cuk converter the two take 0.05-0.1 s to lambdify, b(x) the largest).
    """

    def __init__(self, model: Model, up: dict[str, Artefact]):
        self.n, self.m, self.nh, self.mh, self.p = model.n, model.m, model.n_hat, model.m_hat, model.p
        m_of_x = up["inverse"].expr("m")
        self._terms = {
            "xi": ([model.phi_bar, up["delta"].expr("delta"), model.l, up["bound"].expr("dp_delta"), up["kappa"].expr("kappa"),
                    up["manifold"].expr("p")], model.xi),
            "x": ([model.f_bar, model.g, model.h, up["delta"].expr("b"), up["delta"].expr("c"), m_of_x], model.x),
            "h_m": ([model.h, m_of_x], model.x),
        }
        self._values = model.values
        self._compiled = {}
        self.p_map = model.numeric(up["manifold"].expr("p"), list(model.xi))
        self.kappa = model.numeric(up["kappa"].expr("kappa"), list(model.xi))
        self.L = np.asarray(up["bound"].value("L"))
        self.K = np.asarray(up["stabilise"].values.get("K", np.zeros((model.m, model.n))), dtype=float).reshape(model.m, model.n)
        self.U = model.U

    def _fused(self, which: str):
        if which not in self._compiled:
            terms, args = self._terms[which]
            self._compiled[which] = compile_terms(terms, list(args), self._values)
        return self._compiled[which]

    def at_xi(self, xi: np.ndarray) -> list[np.ndarray]:
        """[phi_bar (n_hat,1), delta (n_hat,m_hat), l (m,1), dp/dxi delta (n,m_hat), kappa (p,1), p (n,1)] at xi."""
        return self._fused("xi")(xi)

    def at_x(self, x: np.ndarray) -> list[np.ndarray]:
        """[f_bar (n,1), g (n,m), h (p,1), b (m_hat,1), c (m_hat,m), m (n_hat,1)] at x."""
        return self._fused("x")(x)

    def h_m(self, x: np.ndarray) -> list[np.ndarray]:
        """[h (p,1), m (n_hat,1)] at x: the m-relation's start and where it stops."""
        return self._fused("h_m")(x)


def _pinv(a: np.ndarray) -> np.ndarray:
    """Moore-Penrose pseudo-inverse, with a cheap path for a single column (zero where the column is)."""
    if a.shape[1] == 1:
        s = float(a[:, 0] @ a[:, 0])
        return a.T / s if s > 0 else np.zeros_like(a.T)
    return np.linalg.pinv(a)


def reference_state(model: Model, plant: _Plant, level: np.ndarray, index: int, kappa: sp.Matrix) -> np.ndarray:
    """The least-norm xi in V with kappa(xi) = level.

    Affine kappa: the quadratic program min ||xi||^2 s.t. K xi + k0 = level, xi in V (cvxpy + Clarabel).
    Scalar abstraction: the roots of kappa - level on a fine grid of V, refined, the smallest kept.
    """
    where = f"simulate.tracking.reference_levels[{index}]"
    if not any(e.free_symbols & set(model.xi) for e in kappa.jacobian(model.xi)):
        K = np.array(model.substitute(kappa.jacobian(model.xi)), dtype=float)
        k0 = np.array(model.substitute(kappa.xreplace({s: 0 for s in model.xi})), dtype=float).reshape(-1)
        xi = cp.Variable(model.n_hat)
        problem = cp.Problem(cp.Minimize(cp.sum_squares(xi)), [K @ xi + k0 == level, xi >= model.V[:, 0], xi <= model.V[:, 1]])
        problem.solve(solver=cp.CLARABEL)
        if xi.value is None or problem.status not in ("optimal", "optimal_inaccurate"):
            raise DesignError(where, f"level {level.tolist()} is not reached by kappa on V ({problem.status})", "levels inside kappa(V)")
        return np.asarray(xi.value, dtype=float)
    if model.n_hat != 1:
        return _reference_state_nonlinear(model, plant, level, where)
    lo, hi = model.V[0]
    grid = np.linspace(lo, hi, 20001)
    err = plant.kappa(grid)[0, 0] - level[0]
    roots = [grid[k] for k in np.flatnonzero(err == 0)]
    for k in np.flatnonzero(np.sign(err[:-1]) * np.sign(err[1:]) < 0):
        roots.append(sopt.brentq(lambda s: plant.kappa(s)[0, 0] - level[0], grid[k], grid[k + 1], xtol=1e-14))
    if not roots:
        k_lo, k_hi = float(np.min(err + level[0])), float(np.max(err + level[0]))
        raise DesignError(where, f"level {level[0]:g} is not reached by kappa on V (kappa(V) = [{k_lo:.6g}, {k_hi:.6g}])",
                          "levels inside kappa(V)")
    return np.array([min(roots, key=abs)])


def _reference_state_nonlinear(model: Model, plant: _Plant, level: np.ndarray, where: str) -> np.ndarray:
    """Several abstract states, nonlinear kappa: bounded least squares on kappa(xi) = level from the points
    of a coarse grid of V; of the exact solutions found, the least-norm one."""
    starts = domain_grid(model.V, 5 ** model.n_hat)
    bounds = (model.V[:, 0], model.V[:, 1])
    found = []
    for start in starts.T:
        fit = sopt.least_squares(lambda s: plant.kappa(*s)[:, 0] - level, start, bounds=bounds, xtol=1e-15, ftol=1e-15, gtol=1e-15)
        if np.abs(fit.fun).max() <= 1e-10 * max(1.0, np.abs(level).max()):
            found.append(fit.x)
    if not found:
        raise DesignError(where, f"level {level.tolist()} is not reached by kappa on V", "levels inside kappa(V)")
    return min(found, key=np.linalg.norm)


def tracking_law(plant: _Plant, xi: np.ndarray, x: np.ndarray, xi_ref: np.ndarray, gain: float, v_max: float,
                 q_kind: str, saturate: bool | str) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """The closed loop at one point: abstract input, interface output, both state derivatives and theta v.

    Returns
    -------
    v : ndarray (m_hat,)
        clip(delta^+ (gain (xi_ref - xi) - phi_bar(xi)), -v_max, v_max).
    u : ndarray (m,)
        u_w = sat(l(xi) + K (x - p(xi)) + q(xi, x) v) (eqs. Interface, egInterface, egInterfaceSat; q = 0 or
        eq. egqLS; K = 0 unless feedback linear_gain).
    dxi, dx : ndarray
        phi_bar(xi) + delta(xi) v and f_bar(x) + g(x) u.
    r : ndarray (n,)
        dp/dxi delta v - g(x) (u - l(xi) - K (x - p(xi))): what drives W away from decay in
        W' <= -lambda W + 2 (p - x)^T M r (eq. iota; r = theta v through sqrt(M)^-1 when u is not clipped).
    """
    phi, delta, l, dpd, _, p = plant.at_xi(xi)
    f_bar, g, *_ = plant.at_x(x)
    v = np.clip(_pinv(delta) @ (gain * (xi_ref - xi) - phi[:, 0]), -v_max, v_max)
    feedback = plant.K @ (x - p[:, 0])   # k(x, p(xi), l(xi)) - l(xi) of eq. Interface (0 for identity feedback)
    u_nominal = l[:, 0] + feedback
    correction = feedback
    if q_kind == "least_squares":
        q = _pinv(plant.L.T @ g) @ (plant.L.T @ dpd)   # argmin ||sqrt(M)(dp/dxi delta - g q)||, eq. egqLS
        correction = correction + q @ v
    u = apply_saturation(l[:, 0], correction, plant.U, saturate)
    return v, u, phi[:, 0] + delta @ v, f_bar[:, 0] + g @ u, dpd @ v - g @ (u - u_nominal)


def sample_times(t0: float, t1: float, dt: float) -> np.ndarray:
    """Sample times t0, t0 + dt, ... strictly below t1, then t1: increasing, never outside [t0, t1].

    (np.arange can overshoot t1 by rounding, which solve_ivp refuses as "not within t_span".)
    """
    n = int(np.floor((t1 - t0) / dt)) + 1
    inner = t0 + dt * np.arange(max(n, 1))
    inner = inner[inner < t1 - 1e-12 * max(1.0, abs(t1))]
    return np.r_[inner, t1]


def _integrate(rhs, t_span, z0, t_eval, tol, what, events=None):
    """solve_ivp with the given tolerances; a failure or a non-finite state is a NumericalError.

    A terminal event (status 1) is returned to the caller, which says what it means.
    """
    with np.errstate(all="ignore"):  # non-finite values are detected below and reported with their time
        sol = sint.solve_ivp(rhs, t_span, z0, t_eval=t_eval, dense_output=False, events=events, **tol)
    if sol.status == 1:
        return sol
    if sol.status != 0 or not np.all(np.isfinite(sol.y)):
        t_bad = sol.t[-1] if sol.t.size else t_span[0]
        raise NumericalError(f"simulate.{what}", f"integration failed at t = {t_bad:.6g} s ({sol.message})", "a trajectory that stays finite")
    return sol


def run_tracking(model: Model, plant: _Plant, up: dict[str, Artefact]) -> tuple[dict, dict]:
    """The tracking scenario; returns (values, checks) with keys under ``tracking/``."""
    tr = model.spec.simulate.tracking
    ctl = tr.abstract_controller
    q_kind, saturate = model.spec.interface.q, model.spec.interface.saturate
    xi0 = np.array(tr.xi0, dtype=float)
    if model.V is not None and not np.all((model.V[:, 0] <= xi0) & (xi0 <= model.V[:, 1])):
        raise DesignError("simulate.tracking.xi0", f"xi0 = {xi0.tolist()} is outside V = {model.V.tolist()}", "xi0 in V")
    x0 = plant.p_map(*xi0)[:, 0] if tr.x0 == "on_manifold" else np.array(tr.x0, dtype=float)
    levels = [np.atleast_1d(np.asarray(level, dtype=float)) for level in tr.reference_levels]
    refs = [reference_state(model, plant, level, i, up["kappa"].expr("kappa")) for i, level in enumerate(levels)]
    nh = model.n_hat

    def rhs_for(xi_ref):
        def rhs(t, z):
            _, _, dxi, dx, r = tracking_law(plant, z[:nh], z[nh:-1], xi_ref, ctl.gain, ctl.v_max, q_kind, saturate)
            # The comparison system of the a-posteriori bound: w' = -(lambda - eps) w + |sqrt(M) r|^2 / eps.
            dw = -(lam - eps) * z[-1] + float(np.sum((plant.L.T @ r) ** 2)) / eps
            return np.r_[dxi, dx, dw]
        return rhs

    lam, eps = float(up["bound"].value("lambda")), float(up["bound"].value("epsilon"))
    alpha_h = float(up["bound"].value("alpha_h"))
    M = np.asarray(up["stabilise"].value("M"))
    e0 = plant.p_map(*xi0)[:, 0] - x0
    W0 = float(e0 @ M @ e0)
    z = np.r_[xi0, x0, W0]
    segments = []   # (t0, t1, sample times, reference index), one per dwell
    t0, k = 0.0, 0
    while t0 < tr.t_final - 1e-12:
        i = min(k, len(levels) - 1)
        # Segment ends as multiples of the dwell (not sums, which drift by rounding).
        t1 = tr.t_final if k >= len(levels) - 1 else min(tr.t_final, (k + 1) * tr.dwell)
        segments.append((t0, t1, sample_times(t0, t1, SAMPLE_DT), i))
        t0, k = t1, k + 1
    try:
        loop = compiled.tracking_loop(model, up) if TRACKING_TOL["method"] == "DOP853" else None
    except compiled.Unsupported:
        loop = None
    if loop is not None:
        res = loop.run(z, segments, refs, gain=ctl.gain, v_max=ctl.v_max, q_kind=q_kind, saturate=saturate,
                       rtol=TRACKING_TOL["rtol"], atol=TRACKING_TOL["atol"])
        t, xi, x, w, idx, v, u, y = res.t, res.xi, res.x, res.w, res.reference_index, res.v, res.u, res.y
        settle = [float(np.abs(res.psi_end[j] - levels[i]).max()) for j, (*_, i) in enumerate(segments)]
    else:
        ts, zs, ref_idx, settle = [], [], [], []
        for t0, t1, t_eval, i in segments:
            sol = _integrate(rhs_for(refs[i]), (t0, t1), z, t_eval, TRACKING_TOL, "tracking")
            keep = slice(None) if not ts else slice(1, None)  # the segment start repeats the previous end
            ts.append(sol.t[keep]); zs.append(sol.y[:, keep]); ref_idx.append(np.full(sol.t[keep].size, i))
            z = sol.y[:, -1]
            settle.append(float(np.abs(plant.at_xi(z[:nh])[4][:, 0] - levels[i]).max()))
        t = np.concatenate(ts)
        Z = np.concatenate(zs, axis=1)
        idx = np.concatenate(ref_idx)
        xi, x, w = Z[:nh], Z[nh:-1], Z[-1]
        v = np.empty((model.m_hat, t.size))
        u = np.empty((model.m, t.size))
        for k in range(t.size):
            v[:, k], u[:, k], *_ = tracking_law(plant, xi[:, k], x[:, k], refs[idx[k]], ctl.gain, ctl.v_max, q_kind, saturate)
        y = np.stack([plant.at_x(x[:, k])[2][:, 0] for k in range(t.size)], axis=1)
    xi_ref = np.stack([refs[i] for i in idx], axis=1)
    psi = plant.kappa(*xi)[:, 0, :]
    e = psi - y
    err = np.linalg.norm(e, axis=0)
    v_inf = float(np.linalg.norm(v, axis=0).max())   # sup over t of |v(t)| (2-norm: theta v is bounded by ||theta|| |v|)
    gain = float(up["bound"].value("gain"))
    bound = gain * v_inf
    span = float(np.ptp(model.Y, axis=1).max())
    # |psi - y| <= alpha_h^-1(W) <= sqrt(w / alpha_h): the a-posteriori bound (comparison lemma on the run's
    # own theta and v), plus the integrator's accuracy, which no simulated error can be held below.
    posterior = np.sqrt(np.maximum(w, 0.0) / alpha_h)
    floor = POSTERIOR_FLOOR_RTOL * max(1.0, span)
    posterior_ok = bool(np.all(err <= posterior + floor))
    e_p = plant.p_map(*xi)[:, 0, :] - x
    W = np.einsum("iN,ij,jN->N", e_p, M, e_p)
    settle_ok = bool(max(settle) <= SETTLE_RTOL * span)
    U = model.U
    u_ok = bool(np.all(u >= U[:, 0:1] - 1e-12) and np.all(u <= U[:, 1:2] + 1e-12))
    xi_ok = bool(np.all(xi >= model.V[:, 0:1] - 1e-9) and np.all(xi <= model.V[:, 1:2] + 1e-9))
    w0_max = float(up["bound"].values.get("w0_max_certified", np.inf))
    v_cert = float(up["bound"].values.get("v_max_certified", np.inf))
    inside = bool(W0 <= w0_max and v_inf <= v_cert)
    region_note = ("the run is inside the certified region" if inside else
                   f"the run is outside the certified region (W0 = {W0:.4g} vs {w0_max:.4g}, ||v||_inf = {v_inf:.4g} vs {v_cert:.4g}): "
                   "the uniform bound is not certified for it, only compared")
    values = {
        "tracking/inside_certified_region": inside, "tracking/compiled": loop is not None,
        "tracking/t": t, "tracking/xi": xi, "tracking/x": x, "tracking/v": v, "tracking/u": u, "tracking/psi": psi,
        "tracking/y": y, "tracking/e_y": e, "tracking/xi_ref": xi_ref, "tracking/reference_levels": np.stack(levels),
        "tracking/reference_index": idx, "tracking/settle_errors": np.array(settle),
        "tracking/max_abs_error": float(err.max()), "tracking/v_inf": v_inf, "tracking/u_min": float(u.min()),
        "tracking/u_max": float(u.max()), "tracking/uniform_bound": bound, "tracking/x0": x0,
        "tracking/W0": W0, "tracking/W": W, "tracking/w_comparison": w, "tracking/posterior_bound": posterior,
        "tracking/posterior_bound_max": float(posterior.max()),
        "tracking/posterior_tightening": float(bound / posterior.max()) if posterior.max() > 0 else float("inf"),
    }
    checks = {
        "tracking_error_within_posterior_bound": Check(float((err - posterior).max()), posterior_ok,
                                                       f"max over the run of |psi - y| - sqrt(w(t) / alpha_h) (<= {POSTERIOR_FLOOR_RTOL:g} x output span, the integrator's accuracy)"),
        "tracking_error_within_bound": Check(float(err.max() - bound), bool(err.max() <= bound), "max |psi - y| - G ||v||_inf (<= 0: eq. egErrorBound holds); " + region_note),
        "tracking_u_in_U": Check(float(max(U[:, 0].max() - u.min(), u.max() - U[:, 1].min())), u_ok, "largest excursion of u outside U (<= 0)"),
        "tracking_settled": Check(max(settle), settle_ok, f"largest |psi - level| at the end of a dwell (<= {SETTLE_RTOL:g} x output span)"),
        "tracking_xi_in_V": Check(float(max((model.V[:, 0:1] - xi).max(), (xi - model.V[:, 1:2]).max())), xi_ok, "largest excursion of xi outside V (<= 0: Theorem ErrorBound applies)"),
    }
    if model.state_box is not None:
        box = model.state_box
        excursion = float(max((box[:, 0:1] - x).max(), (x - box[:, 1:2]).max()))
        checks["tracking_x_in_state_box"] = Check(excursion, excursion <= 0, "largest excursion of x outside concrete.state_box (<= 0: the Jacobian LMI and L_h hold along the run)")
    return values, checks


def run_m_relation(model: Model, plant: _Plant, up: dict[str, Artefact]) -> tuple[dict, dict]:
    """The m-relation scenario; returns (values, checks) with keys under ``m_relation/``.

    The closed loop is integrated by the compiled loop (:func:`ashc_cli.compiled.m_relation_loop`, the same
    right-hand side and event in numba) where it runs, else by solve_ivp; ``m_relation/compiled`` says which.
    """
    mr = model.spec.simulate.m_relation
    names = {**model.params, "t": TIME}
    texts = mr.u if isinstance(mr.u, list) else [mr.u]
    u_expr = sp.Matrix([parse_expression(s, names, f"simulate.m_relation.u[{i}]", signal=True) for i, s in enumerate(texts)])
    x0 = np.array(mr.x0, dtype=float)
    # m (and b, c, built from it) is used only where it is certified: h(x) in inverse.m_domain.
    box, set_name, _ = certified_set(up["inverse"])
    h_x0, m_x0 = plant.h_m(x0)
    y0 = h_x0[:, 0]
    if outside_certified_set(box, y0):
        shown = f"{y0[0]:.6g}" if y0.size == 1 else np.round(y0, 6).tolist()
        raise DesignError("simulate.m_relation.x0", f"y = h(x0) = {shown} is outside the set where m is certified, y in {set_name} = {format_box(box)} (x0 = {x0.tolist()})",
                          f"x0 with h(x0) in {format_box(box)} (inverse.m_domain)")
    xi0 = m_x0[:, 0]
    if not np.all(np.isfinite(xi0)):
        raise DesignError("simulate.m_relation.x0", f"m(x0) is not real at x0 = {x0.tolist()}", "x0 where m is real (see inverse.m_real_interval)")
    nh = model.n_hat

    # One output: the run stops where y = h(x) leaves the certified interval. At an end where m stops being real,
    # kappa turns and dm/dx (so b, c and xi') blows up like 1/sqrt(distance): there it stops a little inside,
    # where the integrator still works. (Several outputs: m_domain is Y, checked at x0 only; the outputs must
    # match along the run, m_relation_outputs_match.)
    inv = up["inverse"]
    d_lo, d_hi = box[0]
    real_lo, real_hi = np.asarray(inv.value("m_real_interval"), dtype=float)
    radical = [str(r) for r in np.atleast_1d(inv.values.get("radicands", ["none"]))] not in (["none"], [])
    tol = DOMAIN_RTOL * max(1.0, d_hi - d_lo)
    lo_edge, hi_edge = bool(radical and d_lo == real_lo), bool(radical and d_hi == real_hi)
    lo_margin = EDGE_MARGIN * (d_hi - d_lo) if lo_edge else -tol
    hi_margin = EDGE_MARGIN * (d_hi - d_lo) if hi_edge else -tol

    def leaves_certified_set(t, z):
        """Positive while y = h(x) is inside the interval where m (and so b, c) is certified (less a margin where m stops being real).

        The compiled loop evaluates the same expression (the core's _leaves, edges [d_lo, lo_margin, d_hi, hi_margin]).
        """
        y = plant.h_m(z[nh:])[0][0, 0]
        return min(y - d_lo - lo_margin, d_hi - hi_margin - y)

    leaves_certified_set.terminal = True
    leaves_certified_set.direction = -1
    bounded = model.p == 1
    z0 = np.r_[xi0, x0]
    if bounded and leaves_certified_set(0.0, z0) <= 0:
        raise DesignError("simulate.m_relation.x0", f"y = h(x0) = {y0[0]:.6g} is within {EDGE_MARGIN:.1%} of the end of {set_name} = {format_box(box)} where m stops being real",
                          f"x0 with h(x0) inside {format_box(box)} (inverse.m_domain)")

    def stopped(t_out: float, z_out: np.ndarray):
        """The DesignError of a run that left the certified set at t_out, in state z_out (the event's root)."""
        y_out = plant.h_m(z_out[nh:])[0][0, 0]
        at_lo = abs(y_out - d_lo) <= abs(y_out - d_hi)
        edge = f" (stopped {EDGE_MARGIN:.1%} short of its end {d_lo if at_lo else d_hi:.6g}, where m stops being real)" if (lo_edge if at_lo else hi_edge) else ""
        return DesignError("simulate.m_relation", f"at t = {t_out:.4g} s the output y = {y_out:.6g} leaves {set_name} = {format_box(box)}, where m is certified{edge}; "
                           f"x = {np.round(z_out[nh:], 4).tolist()}", "a scenario whose output stays where m is certified (inverse.m_domain)")

    t_eval = np.linspace(0.0, mr.t_final, int(round(mr.t_final / SAMPLE_DT)) + 1)
    try:
        loop = compiled.m_relation_loop(model, up, u_expr) if M_RELATION_TOL["method"] == "DOP853" else None
    except compiled.Unsupported:
        loop = None
    if loop is not None:
        res = loop.run(z0, (0.0, mr.t_final), t_eval, edges=[d_lo, lo_margin, d_hi, hi_margin] if bounded else None,
                       rtol=M_RELATION_TOL["rtol"], atol=M_RELATION_TOL["atol"])
        if res.left is not None:
            raise stopped(*res.left)
        t, xi, x, u, v, psi, y, m_x = res.t, res.xi, res.x, res.u, res.v, res.psi, res.y, res.m
    else:
        u_of_t = compile_flat(list(u_expr), [TIME], model.values)

        def rhs(t, z):
            """u(t), v = b(x) + c(x) u (eq. mRelateLink) and both state derivatives."""
            xi, x = z[:nh], z[nh:]
            u = np.array(u_of_t(t), dtype=float)
            phi, delta, *_ = plant.at_xi(xi)
            f_bar, g, _, b, c, _ = plant.at_x(x)
            v = b[:, 0] + c @ u
            return np.r_[phi[:, 0] + delta @ v, f_bar[:, 0] + g @ u]

        sol = _integrate(rhs, (0.0, mr.t_final), z0, t_eval, M_RELATION_TOL, "m_relation", events=[leaves_certified_set] if bounded else None)
        if sol.status == 1:
            raise stopped(sol.t_events[0][0], sol.y_events[0][0])
        t, xi, x = sol.t, sol.y[:nh], sol.y[nh:]
        # The samples in one batch call of each compiled function (N points at once).
        _, _, h_x, b, c, m_of_x = plant.at_x(x)
        u = np.stack([np.broadcast_to(np.asarray(ui, dtype=float), t.shape) for ui in u_of_t(t)])
        v = b[:, :, 0].T + np.einsum("Nij,jN->iN", c, u)
        y, m_x = h_x[:, :, 0].T, m_of_x[:, :, 0].T
        psi = plant.kappa(*xi)[:, 0, :]
    e = psi - y
    err = float(np.linalg.norm(e, axis=0).max())
    invariance = float(np.abs(m_x - xi).max())
    values = {
        "m_relation/t": t, "m_relation/xi": xi, "m_relation/x": x, "m_relation/u": u, "m_relation/v": v,
        "m_relation/psi": psi, "m_relation/y": y, "m_relation/e_y": e, "m_relation/xi0": xi0,
        "m_relation/max_abs_error": err, "m_relation/invariance_residual": invariance,
        "m_relation/u_min": float(u.min()), "m_relation/u_max": float(u.max()), "m_relation/compiled": loop is not None,
    }
    checks = {"m_relation_outputs_match": Check(err, err < M_RELATION_TOL_ABS, f"max |psi - y| over the run (< {M_RELATION_TOL_ABS:g}: Theorem mRelatOutMatch)")}
    return values, checks


def run(model: Model, upstream: dict[str, Artefact]) -> Artefact:
    """Run the spec's tracking and m-relation scenarios.

    Returns
    -------
    Artefact
        Time series and metrics under ``tracking/`` and ``m_relation/``.

    Raises
    ------
    SpecError
        If the spec has no ``simulate`` scenario.
    DesignError
        If a reference level is out of reach or the m-relation run leaves the region where m is real.
    NumericalError
        If an integration fails or blows up.
    """
    sim = model.spec.simulate
    if sim.tracking is None and sim.m_relation is None:
        raise DesignError("simulate", "the spec has no scenario", "simulate.tracking and/or simulate.m_relation")
    plant = _Plant(model, upstream)
    art = Artefact(stage=NAME, meta={"tracking_integrator": TRACKING_TOL, "m_relation_integrator": M_RELATION_TOL,
                                      "sample_dt": SAMPLE_DT, "interface_q": model.spec.interface.q,
                                      "saturate": model.spec.interface.saturate})
    for scenario, runner in (("tracking", run_tracking), ("m_relation", run_m_relation)):
        if getattr(sim, scenario) is not None:
            values, checks = runner(model, plant, upstream)
            art.values.update(values)
            # Which DOP853 ran (the same method and tolerances either way).
            code = "ashc_cli.compiled (numba)" if values[f"{scenario}/compiled"] else "scipy.integrate.solve_ivp"
            art.meta[f"{scenario}_integrator"] = {**art.meta[f"{scenario}_integrator"], "implementation": code}
            # Observed along one simulated run: evidence "simulated", never a proof.
            art.checks.update({k: replace(c, evidence=SIMULATED) for k, c in checks.items()})
    return art


_METRICS = {
    "tracking": ("max_abs_error", "v_inf", "u_min", "u_max", "uniform_bound", "W0", "posterior_bound_max", "posterior_tightening"),
    "m_relation": ("max_abs_error", "invariance_residual", "u_min", "u_max"),
}


def summarise(art: Artefact) -> dict:
    """Headline numbers for ``ashc summary``."""
    out = {}
    for scenario, keys in _METRICS.items():
        if f"{scenario}/t" in art.values:
            out[scenario] = {k: float(art.values[f"{scenario}/{k}"]) for k in keys}
    if "tracking" in out:
        out["tracking"]["settle_errors"] = np.asarray(art.values["tracking/settle_errors"]).tolist()
    return out


def headline(art: Artefact) -> str:
    """One progress line."""
    parts = []
    if "tracking/t" in art.values:
        v = art.values
        post = f" (a posteriori {v['tracking/posterior_bound_max']:.4g})" if "tracking/posterior_bound_max" in v else ""
        parts.append(f"tracking max|psi - y| = {v['tracking/max_abs_error']:.4g} <= {v['tracking/uniform_bound']:.5g}{post}")
    if "m_relation/t" in art.values:
        parts.append(f"m-relation max|psi - y| = {art.values['m_relation/max_abs_error']:.2g}")
    failed = failed_checks(art)
    if failed:
        parts.append("FAILED (simulated): " + "; ".join(f"{name} = {chk.value:.4g}" for name, chk in failed.items()))
    return ", ".join(parts)


def failed_checks(art: Artefact) -> dict:
    """The scenario checks that did not pass (shown by ``simulate``, ``ashc check`` and the report)."""
    return {name: chk for name, chk in art.checks.items() if not chk.passed}
