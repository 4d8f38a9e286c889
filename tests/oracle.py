"""The tests' oracle of the compiled closed loops: scipy's solve_ivp on the closed-loop laws written in numpy,
one point at a time (the set-point law, the guaranteed governor with the interface and its saturation: the same
right-hand sides as the compiled cores, :mod:`ashc_cli.closedloop.tracking_core` and :mod:`ashc_cli.closedloop.governor`).

:class:`TrackingOracle` and :class:`MRelationOracle` have the ``run`` of the compiled loops
(:class:`ashc_cli.closedloop.compiled.TrackingLoop`, :class:`~ashc_cli.closedloop.compiled.MRelationLoop`) and
return the same records, so a test hands them to ``simulate`` in place of the compiled loop (``simulate.tracking_loop_for``,
``compiled.m_relation_loop``) and compares whole scenarios.
"""

from __future__ import annotations

import numpy as np
import scipy.integrate as sint

from ashc_cli.closedloop.compiled import MRelationRun, TrackingRun
from ashc_cli.closedloop.batch import BatchPlant, interface
from ashc_cli.closedloop.plan import GOVERNOR_BACKOFF, GOVERNOR_BISECTIONS, GOVERNOR_GRID, Law
from ashc_cli.closedloop.terms import DesignTerms
from ashc_cli.numerics.linalg import pinv
from ashc_cli.errors import NumericalError
from ashc_cli.problem.model import TIME, Model, compile_flat


def apply_saturation(l: np.ndarray, correction: np.ndarray, U: np.ndarray, mode) -> np.ndarray:
    """SAT of eq. (44) written here in numpy, apart from the tool's (closedloop/interface.py): the oracle's own."""
    u = l + correction
    if mode == "scale":
        lo, hi = U[:, 0], U[:, 1]
        with np.errstate(divide="ignore", invalid="ignore"):
            room = np.where(correction > 0, (hi - l) / correction, np.where(correction < 0, (lo - l) / correction, np.inf))
        s = np.clip(np.min(room, axis=-1, keepdims=True), 0.0, 1.0)
        return l + s * correction
    if mode:
        return np.clip(u, U[:, 0], U[:, 1])
    return u


def tracking_law(plant: DesignTerms, xi: np.ndarray, x: np.ndarray, xi_ref: np.ndarray, gain: float, v_max: float,
                 q_kind: str, saturate: bool | str) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """The closed loop at one point: abstract input, interface output, both state derivatives and theta v.

    Returns
    -------
    v : ndarray (m_hat,)
        clip(delta^+ (gain (xi_ref - xi) - phi_bar(xi)), -v_max, v_max).
    u : ndarray (m,)
        u_w = sat(l(xi) + K (x - p(xi)) + q(xi, x) v) (eqs. (15), (42), (44); q = 0 or
        eq. (43); K = 0 unless feedback linear_gain).
    dxi, dx : ndarray
        phi_bar(xi) + delta(xi) v and f_bar(x) + g(x) u.
    r : ndarray (n,)
        dp/dxi delta v - g(x) (u - l(xi) - K (x - p(xi))): what drives W away from decay in
        W' <= -lambda W + 2 (p - x)^T M r (eq. (37); r = theta v through sqrt(M)^-1 when u is not clipped).
    """
    phi, delta, l, dpd, _, p = plant.at_xi(xi)
    f_bar, g, *_ = plant.at_x(x)
    v = np.clip(pinv(delta) @ (gain * (xi_ref - xi) - phi[:, 0]), -v_max, v_max)
    feedback = plant.K @ (x - p[:, 0])   # k(x, p(xi), l(xi)) - l(xi) of eq. (15) (0 for identity feedback)
    u_nominal = l[:, 0] + feedback
    correction = feedback
    if q_kind == "least_squares":
        q = pinv(plant.L.T @ g) @ (plant.L.T @ dpd)   # argmin ||sqrt(M)(dp/dxi delta - g q)||, eq. (43)
        correction = correction + q @ v
    u = apply_saturation(l[:, 0], correction, plant.U, saturate)
    return v, u, phi[:, 0] + delta @ v, f_bar[:, 0] + g @ u, dpd @ v - g @ (u - u_nominal)


def interface_r(s: np.ndarray, L: np.ndarray, l: np.ndarray, feedback: np.ndarray, qv: np.ndarray, dv: np.ndarray,
                 g: np.ndarray, U: np.ndarray, saturate) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """u(s), r(s) and |L^T r(s)|^2 for v = s v_sp, at each s of an array (one point (xi, x)).

    u(s) = SAT(l + K e + s q v_sp) (the actual interface, eqs. (15), (44)) and
    r(s) = s dp/dxi delta v_sp - g (u(s) - l - K e) (eq. (37): what drives W in W' <= -(lambda - eps) W + |L^T r|^2 / eps).
    """
    s = np.atleast_1d(np.asarray(s, dtype=float))
    u = apply_saturation(l, feedback + s[:, None] * qv, U, saturate)          # (N, m)
    r = s[:, None] * dv - (u - l - feedback) @ g.T                            # (N, n)
    return u, r, np.sum((r @ L) ** 2, axis=1)


def breakpoints(l: np.ndarray, feedback: np.ndarray, qv: np.ndarray, U: np.ndarray, saturate) -> tuple[list[float], bool]:
    """The s in (0, 1) where the interface changes form, and whether r(s) is affine between them.

    ``saturate: true`` clips each channel of l + K e + s q v_sp, an affine function of s: the pieces end where a
    channel meets a bound.  ``scale`` with K e = 0 applies min(s, s_c) q v_sp: one end, s_c.  ``false``: no end.
    ``scale`` with K e != 0 is not piecewise affine in s (the factor divides the whole correction).
    """
    if saturate is False:
        return [], True
    if saturate == "scale" and np.any(feedback):
        return [], False
    ends, s_c = set(), np.inf
    for j in range(qv.size):                        # a few channels: plain floats are faster than arrays here
        d = float(qv[j])
        if d == 0.0:
            continue
        lo = (float(U[j, 0]) - float(l[j]) - float(feedback[j])) / d
        hi = (float(U[j, 1]) - float(l[j]) - float(feedback[j])) / d
        if saturate is True:
            ends.update(e for e in (lo, hi) if 0.0 < e < 1.0)
        else:
            s_c = min(s_c, hi if d > 0 else lo)
    if saturate == "scale" and 0.0 < s_c < 1.0:
        ends.add(s_c)
    return sorted(ends), True


def governor_scale(L: np.ndarray, l: np.ndarray, feedback: np.ndarray, qv: np.ndarray, dv: np.ndarray, g: np.ndarray,
                   U: np.ndarray, saturate, bound: float) -> tuple[float, np.ndarray, np.ndarray, bool]:
    """The largest s in [0, 1] with |L^T r(s)|^2 <= bound, r(s) through the actual interface (:func:`interface_r`).

    Where r is piecewise affine in s (every ``saturate`` but ``scale`` with K e != 0), |L^T r(s)|^2 is a convex
    quadratic on each piece, and the largest admissible s of a piece is a root found in closed form; the pieces
    are searched from s = 1 down.  Elsewhere a grid of GOVERNOR_GRID + 1 values of s, then bisection between the
    largest admissible one and the next.  Every s returned has been evaluated and found admissible: a root that
    rounding puts just outside is bisected back inside.

    Parameters
    ----------
    L : ndarray (n, n)
        M = L L^T.
    l, feedback, qv : ndarray (m,)
        l(xi), K (x - p(xi)) and q(xi, x) v_sp.
    dv : ndarray (n,)
        dp/dxi delta(xi) v_sp.
    g : ndarray (n, m)
        g(x).
    U : ndarray (m, 2)
        The input box.
    saturate : bool or str
        ``interface.saturate``.
    bound : float
        eps ((lambda - eps) W_max + c (W_max - w)).

    Returns
    -------
    s : float
    u, r : ndarray
        u(s) and r(s), as evaluated when s was accepted.
    admissible : bool
        False only when not even s = 0 is admissible (r(0) != 0: K e clipped, outside the region of the proof);
        s = 0 is returned then.
    """
    def at(s_values):
        return interface_r(s_values, L, l, feedback, qv, dv, g, U, saturate)

    def largest_verified(lo: float, hi: float):
        """The largest s in [lo, hi] found admissible by evaluation: hi, or hi a few roundings lower (a root in
        closed form is accurate to a few ulps), else bisection from lo."""
        for back in GOVERNOR_BACKOFF:
            s_try = max(lo, hi * (1.0 - back))
            u, r, q2 = at(s_try)
            if q2[0] <= bound:
                return s_try, u[0], r[0]
        u, r, q2 = at(lo)
        if not q2[0] <= bound:
            return None
        good = (lo, u[0], r[0])
        for _ in range(GOVERNOR_BISECTIONS):
            mid = 0.5 * (good[0] + hi)
            if not good[0] < mid < hi:
                break
            u, r, q2 = at(mid)
            if q2[0] <= bound:
                good = (mid, u[0], r[0])
            else:
                hi = mid
        return good

    ends, affine = breakpoints(l, feedback, qv, U, saturate)
    grid = np.array([0.0, *ends, 1.0]) if affine else np.linspace(0.0, 1.0, GOVERNOR_GRID + 1)
    u, r, q2 = at(grid)
    ok = q2 <= bound
    if ok[-1]:
        return 1.0, u[-1], r[-1], True
    if affine:
        R = r @ L
        for k in range(grid.size - 2, -1, -1):
            s0, s1 = grid[k], grid[k + 1]
            if ok[k + 1]:
                return float(s1), u[k + 1], r[k + 1], True
            h = s1 - s0
            D = (R[k + 1] - R[k]) / h
            a, b, c0 = float(D @ D), float(R[k] @ D), float(R[k] @ R[k]) - bound
            if a <= 0.0:
                continue                                    # constant on the piece and inadmissible at its end
            disc = b * b - a * c0
            if disc < 0.0:
                continue
            root = np.sqrt(disc)
            upper = -c0 / (b + root) if b > 0 else (root - b) / a         # the larger root, without cancellation
            lower = (-b - root) / a if b > 0 else (c0 / (a * upper) if upper != 0 else (-b - root) / a)
            if upper < 0.0 or lower > h:
                continue
            found = largest_verified(s0 + max(lower, 0.0), s0 + min(upper, h))
            if found is not None:
                return float(found[0]), found[1], found[2], True
    else:
        k = np.flatnonzero(ok)
        if k.size:
            found = largest_verified(float(grid[k[-1]]), float(grid[k[-1] + 1]))
            if found is not None:
                return float(found[0]), found[1], found[2], True
    return 0.0, u[0], r[0], bool(ok[0])


def governor_law(plant: DesignTerms, xi: np.ndarray, x: np.ndarray, w: float, xi_ref: np.ndarray, law: Law, q_kind: str, saturate,
                 lam: float, eps: float) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray, float, float]:
    """The governed closed loop at one point (docs/guaranteed.md).

    v = s v_sp, v_sp = clip(delta^+ (gain (xi_ref - xi) - phi_bar), -v_max, v_max), with the largest s in [0, 1]
    such that |L^T r|^2 / eps <= (lambda - eps) W_max + c (W_max - w) (:func:`governor_scale`): then the comparison
    system w' = -(lambda - eps) w + |L^T r|^2 / eps satisfies w' <= (lambda - eps + c) (W_max - w), so w <= W_max
    is invariant.

    Returns
    -------
    v, u, dxi, dx, r : ndarray
        As :func:`tracking_law`.
    s : float
        The scale applied to v_sp.
    slack : float
        (lambda - eps) W_max + c (W_max - w) - |L^T r|^2 / eps (>= 0 where the condition holds).
    """
    phi, delta, l, dpd, _, p = plant.at_xi(xi)
    f_bar, g, *_ = plant.at_x(x)
    v_sp = np.clip(pinv(delta) @ (law.gain * (xi_ref - xi) - phi[:, 0]), -law.v_max, law.v_max)
    feedback = plant.K @ (x - p[:, 0])
    q = pinv(plant.L.T @ g) @ (plant.L.T @ dpd) if q_kind == "least_squares" else np.zeros((g.shape[1], v_sp.size))
    room = (lam - eps) * law.w_level + law.rate * (law.w_level - w)
    s, u, r, _ = governor_scale(plant.L, l[:, 0], feedback, q @ v_sp, dpd @ v_sp, g, plant.U, saturate, eps * room)
    v = s * v_sp
    slack = room - float(np.sum((plant.L.T @ r) ** 2)) / eps
    return v, u, phi[:, 0] + delta @ v, f_bar[:, 0] + g @ u, r, s, slack



# --- falsify's loop in numpy on a batch of points (the compiled falsify runs' oracle) ---------------------------


def _mv(A: np.ndarray, v: np.ndarray) -> np.ndarray:
    """A stack of matrices (N, r, c) times a stack of vectors (N, c)."""
    return (A @ v[:, :, None])[:, :, 0]


def batch_apply(model: Model, pre: dict, v: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """u, xi', x' for the batch with input v (N, m_hat): u = sat(l + K (x - p) + q v).

    Parameters
    ----------
    model : Model
    pre : dict
        From :func:`interface`.
    v : ndarray (N, m_hat)
    """
    a, b = pre["a"], pre["b"]
    u = apply_saturation(a["l"][:, :, 0], pre["kx"] + _mv(pre["q"], v), model.U, model.spec.interface.saturate)
    dxi = a["phi"][:, :, 0] + _mv(a["delta"], v)
    dx = b["f_bar"][:, :, 0] + _mv(b["g"], u)
    return u, dxi, dx


def batch_controls(model: Model, plant: BatchPlant, xi: np.ndarray, x: np.ndarray, v: np.ndarray
              ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """v, u, xi' and x' for the batch (shapes (N, m_hat), (N, m), (N, n_hat), (N, n)) with the interface
    u = sat(l(xi) + K (x - p(xi)) + q(xi, x) v) (model.apply_saturation) and the two systems.

    Parameters
    ----------
    model : Model
    plant : BatchPlant
    xi, x : ndarray (n_hat, N), (n, N)
    v : ndarray (N, m_hat)
    """
    u, dxi, dx = batch_apply(model, interface(model, plant, xi, x), v)
    return v, u, dxi, dx


def integrate(rhs, t_span, z0, t_eval, tol, what, events=None):
    """solve_ivp with the given tolerances (``tol``: method, rtol, atol); a failure or a non-finite state is a
    NumericalError, a terminal event (status 1) is returned."""
    with np.errstate(all="ignore"):
        sol = sint.solve_ivp(rhs, t_span, z0, t_eval=t_eval, dense_output=False, events=events, **tol)
    if sol.status == 1:
        return sol
    if sol.status != 0 or not np.all(np.isfinite(sol.y)):
        t_bad = sol.t[-1] if sol.t.size else t_span[0]
        raise NumericalError(f"simulate.{what}", f"integration failed at t = {t_bad:.6g} s ({sol.message})", "a trajectory that stays finite")
    return sol


class TrackingOracle:
    """The tracking (set-point or governor) closed loop and its comparison system on solve_ivp."""

    compiled = False

    def __init__(self, model, plant, up, law: Law, method: str = "DOP853"):
        self.model, self.plant, self.law, self.method = model, plant, law, method
        self.lam, self.eps = float(up["bound"].value("lambda")), float(up["bound"].value("epsilon"))

    def _law(self, z, xi_ref, gain, v_max, q_kind, saturate):
        nh, law = self.model.n_hat, self.law
        if law.kind == "governor":
            v, u, dxi, dx, r, s, slack = governor_law(self.plant, z[:nh], z[nh:-1], z[-1], xi_ref, law, q_kind, saturate, self.lam, self.eps)
        else:
            v, u, dxi, dx, r = tracking_law(self.plant, z[:nh], z[nh:-1], xi_ref, gain, v_max, q_kind, saturate)
            s = slack = None
        # The comparison system of the a-posteriori bound: w' = -(lambda - eps) w + |L^T r|^2 / eps.
        dw = -(self.lam - self.eps) * z[-1] + float(np.sum((self.plant.L.T @ r) ** 2)) / self.eps
        return v, u, np.r_[dxi, dx, dw], s, slack

    def run(self, z0, segments, refs, *, gain, v_max, q_kind, saturate, rtol, atol, governor=None, law=None) -> TrackingRun:
        """As :meth:`ashc_cli.closedloop.compiled.TrackingLoop.run` (``law``, the compiled one, is not read: the
        oracle runs its own set-point law or governor, as its Law says)."""
        nh = self.model.n_hat
        z = np.asarray(z0, dtype=float)
        ts, zs, idx, psi_end = [], [], [], []
        tol = {"method": self.method, "rtol": rtol, "atol": atol}
        for t0, t1, t_eval, i in segments:
            sol = integrate(lambda t, y, i=i: self._law(y, refs[i], gain, v_max, q_kind, saturate)[2], (t0, t1), z, t_eval, tol, "tracking")
            keep = slice(None) if not ts else slice(1, None)      # the segment start repeats the previous end
            ts.append(sol.t[keep])
            zs.append(sol.y[:, keep])
            idx.append(np.full(sol.t[keep].size, i))
            z = sol.y[:, -1]
            psi_end.append(self.plant.at_xi(z[:nh])[4][:, 0])
        t, Z, index = np.concatenate(ts), np.concatenate(zs, axis=1), np.concatenate(idx)
        laws = [self._law(Z[:, k], refs[index[k]], gain, v_max, q_kind, saturate) for k in range(t.size)]
        v, u = np.stack([a[0] for a in laws], axis=1), np.stack([a[1] for a in laws], axis=1)
        psi = np.stack([self.plant.at_xi(Z[:nh, k])[4][:, 0] for k in range(t.size)], axis=1)
        y = np.stack([self.plant.at_x(Z[nh:-1, k])[2][:, 0] for k in range(t.size)], axis=1)
        scale = np.array([a[3] for a in laws]) if self.law.kind == "governor" else None
        slack = np.array([a[4] for a in laws]) if self.law.kind == "governor" else None
        return TrackingRun(t=t, xi=Z[:nh], x=Z[nh:-1], w=Z[-1], v=v, u=u, psi=psi, y=y, reference_index=index,
                           psi_end=np.array(psi_end), nfev=0, steps=0, scale=scale, slack=slack)


class MRelationOracle:
    """The m-relation's open loop and its link v = b(x) + c(x) u (eq. (38)) on solve_ivp, with the terminal event of
    the compiled loop's ``edges``."""

    compiled = False

    def __init__(self, model, plant, u_expr, method: str = "DOP853"):
        self.model, self.plant, self.method = model, plant, method
        self.u_of_t = compile_flat(list(u_expr), [TIME], model.values)

    def rhs(self, t, z):
        nh = self.model.n_hat
        u = np.array(self.u_of_t(t), dtype=float)
        phi, delta, *_ = self.plant.at_xi(z[:nh])
        f_bar, g, _, b, c, _ = self.plant.at_x(z[nh:])
        v = b[:, 0] + c @ u
        return np.r_[phi[:, 0] + delta @ v, f_bar[:, 0] + g @ u]

    def run(self, z0, t_span, t_eval, *, edges, rtol, atol) -> MRelationRun:
        """As :meth:`ashc_cli.closedloop.compiled.MRelationLoop.run` (``left`` = (t, z) where the run left)."""
        nh = self.model.n_hat
        events = None
        if edges is not None:
            lo, lo_margin, hi, hi_margin = edges

            def leaves(t, z):
                y = self.plant.h_m(z[nh:])[0][0, 0]
                return min(y - lo - lo_margin, hi - hi_margin - y)
            leaves.terminal, leaves.direction = True, -1
            events = [leaves]
        tol = {"method": self.method, "rtol": rtol, "atol": atol}
        sol = integrate(self.rhs, (float(t_span[0]), float(t_span[1])), np.asarray(z0, dtype=float), t_eval, tol, "m_relation", events)
        if sol.status == 1:
            empty = np.empty((0, 0))
            return MRelationRun(t=np.empty(0), xi=empty, x=empty, u=empty, v=empty, psi=empty, y=empty, m=empty,
                                left=(float(sol.t_events[0][0]), sol.y_events[0][0].copy()), nfev=sol.nfev, steps=0)
        t, xi, x = sol.t, sol.y[:nh], sol.y[nh:]
        _, _, h_x, b, c, m_of_x = self.plant.at_x(x)
        u = np.stack([np.broadcast_to(np.asarray(ui, dtype=float), t.shape) for ui in self.u_of_t(t)])
        v = b[:, :, 0].T + np.einsum("Nij,jN->iN", c, u)
        return MRelationRun(t=t, xi=xi, x=x, u=u, v=v, psi=self.plant.kappa(*xi)[:, 0, :], y=h_x[:, :, 0].T, m=m_of_x[:, :, 0].T,
                            left=None, nfev=sol.nfev, steps=0)


def use_oracles(monkeypatch, simulate, method: str = "DOP853"):
    """Make ``simulate`` run its scenarios on the oracles (solve_ivp) instead of the compiled loops."""
    from ashc_cli.closedloop import runner

    oracle = lambda model, up, law: TrackingOracle(model, simulate.DesignTerms(model, up), up, law, method)     # noqa: E731
    monkeypatch.setattr(simulate, "tracking_loop_for", oracle)
    monkeypatch.setattr(runner, "tracking_loop_for", oracle)       # the task's run and the products call it there
    monkeypatch.setattr(simulate.compiled, "m_relation_loop",
                        lambda model, up, u: MRelationOracle(model, simulate.DesignTerms(model, up), u, method))
