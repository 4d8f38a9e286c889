"""The tests' oracle of the compiled closed loops: scipy's solve_ivp on the numpy laws of
:mod:`ashc_cli.closedloop.reference` (the same right-hand sides, written in numpy).

:class:`TrackingOracle` and :class:`MRelationOracle` have the ``run`` of the compiled loops
(:class:`ashc_cli.closedloop.compiled.TrackingLoop`, :class:`~ashc_cli.closedloop.compiled.MRelationLoop`) and
return the same records, so a test hands them to ``simulate`` in place of the compiled loop (``simulate.tracking_loop_for``,
``compiled.m_relation_loop``) and compares whole scenarios.
"""

from __future__ import annotations

import numpy as np
import scipy.integrate as sint

from ashc_cli.closedloop.compiled import MRelationRun, TrackingRun
from ashc_cli.closedloop.reference import Law, governor_law, tracking_law
from ashc_cli.errors import NumericalError
from ashc_cli.problem.model import TIME, compile_flat


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

    def run(self, z0, segments, refs, *, gain, v_max, q_kind, saturate, rtol, atol, governor=None) -> TrackingRun:
        """As :meth:`ashc_cli.closedloop.compiled.TrackingLoop.run`."""
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
    monkeypatch.setattr(simulate, "tracking_loop_for", lambda model, up, law: TrackingOracle(model, simulate.DesignTerms(model, up), up, law, method))
    monkeypatch.setattr(simulate.compiled, "m_relation_loop",
                        lambda model, up, u: MRelationOracle(model, simulate.DesignTerms(model, up), u, method))
