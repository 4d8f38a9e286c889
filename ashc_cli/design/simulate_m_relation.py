"""The m-relation scenario of ``simulate`` (Theorem 3, Figs. 9 and 10): the plant open loop under the spec's u(t), the
abstraction driven by the link v = b(x) + c(x) u (v = b(x, u) for a plant written as f(x, u)) from xi0 = m(x0), both
integrated by the compiled loop (:func:`ashc_cli.closedloop.compiled.m_relation_loop`); and how runs are sampled."""

from __future__ import annotations

import numpy as np
import sympy as sp

from ashc_cli.closedloop import compiled
from ashc_cli.closedloop.runner import MAX_RUN_SAMPLES, SAMPLE_DT, sample_dt  # noqa: F401  (the run's sampling, re-exported)
from ashc_cli.closedloop.terms import DesignTerms
from ashc_cli.design.artefacts import Artefact, Check
from ashc_cli.design.upstream import DOMAIN_RTOL, certified_set, format_box, outside_certified_set
from ashc_cli.errors import DesignError, NumericalError, ScenarioStopped
from ashc_cli.problem.expr import parse_expression
from ashc_cli.problem.model import TIME, Model

__all__ = ["run_m_relation", "sample_dt", "SAMPLE_DT", "MAX_RUN_SAMPLES", "M_RELATION_TOL", "M_RELATION_TOL_ABS", "EDGE_MARGIN"]

M_RELATION_TOL = {"method": "DOP853", "rtol": 1e-11, "atol": 1e-11}
#: m-relation: outputs must match to this (V), Theorem 3.
M_RELATION_TOL_ABS = 1e-6
#: The m-relation run stops when y comes this close (fraction of the certified interval) to an end where m
#: stops being real (there dm/dx blows up); at the other ends of the certified set it stops on the end.
EDGE_MARGIN = 1e-3



def run_m_relation(model: Model, plant: DesignTerms, up: dict[str, Artefact]) -> tuple[dict, dict]:
    """The m-relation scenario; returns (values, checks) with keys under ``m_relation/``.

    The closed loop is integrated by the compiled loop (:func:`ashc_cli.closedloop.compiled.m_relation_loop`, the same
    right-hand side and event in numba, on the engine of :mod:`ashc_cli.closedloop.rk`).

    Parameters
    ----------
    model : Model
        The spec's systems (``simulate.m_relation``: u(t), x0, t_final).
    plant : DesignTerms
        The design's compiled terms (h and m at x0 and where the run stops).
    up : dict of str to Artefact
        The artefacts of stabilise .. bound, by stage (``inverse`` gives where m is certified).

    Returns
    -------
    values : dict
        Time series and metrics, by artefact key.
    checks : dict of str to Check

    Raises
    ------
    DesignError
        If h(x0) is outside (or, one output, at the edge of) the set where m is certified, m(x0) is not real, or the run
        leaves that set (:class:`~ashc_cli.errors.ScenarioStopped`).
    NumericalError
        If the loop cannot be compiled.
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
    # outputs augmented with states (n_hat > p, inverse.meta.augmented_outputs): the box is in (h, x_J), the inverse's h
    y_cert = y0 if len(box) == y0.size else np.asarray(model.numeric(up["inverse"].expr("h"), list(model.x))(*x0), dtype=float).reshape(-1)
    if outside_certified_set(box, y_cert):
        shown = f"{y_cert[0]:.6g}" if y_cert.size == 1 else np.round(y_cert, 6).tolist()
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

    bounded = model.p == 1
    z0 = np.r_[xi0, x0]
    # The run stops where y = h(x) leaves [d_lo + lo_margin, d_hi - hi_margin] (the compiled loop's event).
    if bounded and min(y0[0] - d_lo - lo_margin, d_hi - hi_margin - y0[0]) <= 0:
        raise DesignError("simulate.m_relation.x0", f"y = h(x0) = {y0[0]:.6g} is within {EDGE_MARGIN:.1%} of the end of {set_name} = {format_box(box)} where m stops being real",
                          f"x0 with h(x0) inside {format_box(box)} (inverse.m_domain)")

    def stopped(t_out: float, z_out: np.ndarray):
        """The ScenarioStopped of a run that left the certified set at t_out, in state z_out (the event's root)."""
        y_out = plant.h_m(z_out[nh:])[0][0, 0]
        at_lo = abs(y_out - d_lo) <= abs(y_out - d_hi)
        edge = f" (stopped {EDGE_MARGIN:.1%} short of its end {d_lo if at_lo else d_hi:.6g}, where m stops being real)" if (lo_edge if at_lo else hi_edge) else ""
        return ScenarioStopped("simulate.m_relation", f"at t = {t_out:.4g} s the output y = {y_out:.6g} leaves {set_name} = {format_box(box)}, where m is certified{edge}; "
                           f"x = {np.round(z_out[nh:], 4).tolist()}", "a scenario whose output stays where m is certified (inverse.m_domain)")

    t_eval = np.linspace(0.0, mr.t_final, int(round(mr.t_final / sample_dt(mr.t_final))) + 1)
    try:
        loop = compiled.m_relation_loop(model, up, u_expr)
    except compiled.Unsupported as exc:
        raise NumericalError("simulate.m_relation", str(exc), "a design the compiled closed loop can run (numba, ASHC_COMPILED unset)") from exc
    res = loop.run(z0, (0.0, mr.t_final), t_eval, edges=[d_lo, lo_margin, d_hi, hi_margin] if bounded else None,
                   rtol=M_RELATION_TOL["rtol"], atol=M_RELATION_TOL["atol"])
    if res.left is not None:
        raise stopped(*res.left)
    t, xi, x, u, v, psi, y, m_x = res.t, res.xi, res.x, res.u, res.v, res.psi, res.y, res.m
    e = psi - y
    err = float(np.linalg.norm(e, axis=0).max())
    invariance = float(np.abs(m_x - xi).max())
    values = {
        "m_relation/t": t, "m_relation/xi": xi, "m_relation/x": x, "m_relation/u": u, "m_relation/v": v,
        "m_relation/psi": psi, "m_relation/y": y, "m_relation/e_y": e, "m_relation/xi0": xi0,
        "m_relation/max_abs_error": err, "m_relation/invariance_residual": invariance,
        "m_relation/u_min": float(u.min()), "m_relation/u_max": float(u.max()), "m_relation/compiled": getattr(loop, "compiled", True),
    }
    checks = {"m_relation_outputs_match": Check(err, err < M_RELATION_TOL_ABS, f"max |psi - y| over the run (< {M_RELATION_TOL_ABS:g}: Theorem 3)")}
    return values, checks
