"""The guaranteed controller's plan for one run (docs/guaranteed.md): what the budget and the governor can certify
from the start's W0, and the abstract controller (:class:`Law`) that the compiled loops
(:mod:`ashc_cli.closedloop.tracking_core`, :mod:`ashc_cli.closedloop.governor`) run."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ashc_cli.errors import DesignError

#: Bisection steps of the governor's search for s where the interface is not piecewise affine in s.
GOVERNOR_BISECTIONS = 60


#: Relative steps back from a root of the governor's quadratic tried before bisecting (rounding puts it a few
#: ulps either side of the boundary).
GOVERNOR_BACKOFF = (0.0, 1e-13, 1e-11)


#: Grid of s in [0, 1] searched first where the interface is not piecewise affine in s (saturate: scale, K e != 0).
GOVERNOR_GRID = 64


@dataclass(frozen=True)
class Law:
    """The abstract controller that closes a tracking run.

    Attributes
    ----------
    kind : str
        ``setpoint`` (the set-point law, also the budget mode) or ``governor``.
    gain : float
        The set-point gain.
    v_max : float
        Elementwise clip of the set-point law (the governor's v_sp: v_max_certified / sqrt(m_hat), inf when the
        bound is global).
    w_level : float
        Governor: the level W_max that it keeps w below.
    rate : float
        Governor: the design constant c.
    params : tuple of float
        A registered controller's further parameters (``abstract_controller.params``).
    """

    kind: str
    gain: float
    v_max: float
    w_level: float = np.inf
    rate: float = 0.0
    params: tuple = ()


#: Governor: the design constant c of its invariance condition |L^T r|^2 / eps <= (lambda - eps) W_max + c (W_max - w),
#: as a multiple of lambda - eps (docs/guaranteed.md).  Any c >= 0 keeps w <= W_max; a larger c spends the room
#: below W_max faster.
GOVERNOR_RATE = 1.0


#: Governor: the level it keeps invariant is (1 - GOVERNOR_MARGIN) tolerance^2 alpha_h, so that the integrator's
#: error on w (rtol, atol 1e-9) cannot carry the simulated w over tolerance^2 alpha_h, the level the proof needs.
GOVERNOR_MARGIN = 1e-6


#: Budget refusal: the least tolerance quoted is sqrt(W0 / alpha_h) (1 + BUDGET_MARGIN), which leaves a v_max > 0.
BUDGET_MARGIN = 1e-2


@dataclass(frozen=True)
class GuaranteedPlan:
    """What a guaranteed controller can certify for one run (eq. (9), docs/guaranteed.md).

    Attributes
    ----------
    tolerance : float
        The spec's EPS.
    mode : str
        The mode that runs: ``budget`` or ``governor`` (``auto`` resolved).
    requested : str
        The spec's mode (``auto``, ``budget`` or ``governor``).
    W0, alpha_h, gain_G : float
        W(xi0, x0), alpha_h and the gain G of eq. (38).
    budget_v_max : float
        The largest |v| (2-norm) with sqrt(W0 / alpha_h) + G |v| + G_w ||w||_inf <= EPS (the disturbance's term when
        the spec has one, at its bound), capped by v_max_certified (with w); NaN when none exists.
    budget_tolerance : float
        sqrt(W0 / alpha_h) + G budget_v_max + G_w ||w||_inf: what the budget mode proves (<= EPS).
    budget_refusal : str or None
        Why the budget mode cannot run (None when it can).
    governor_level : float
        W_max = (1 - GOVERNOR_MARGIN) min(EPS^2 alpha_h, w0_max_certified), the level the governor keeps w below
        (the margin absorbs the integrator's error on w).
    governor_tolerance : float
        sqrt(min(EPS^2 alpha_h, w0_max_certified) / alpha_h): what the governor proves (<= EPS).
    governor_refusal : str or None
        Why the governor cannot run (None when it can).
    """

    tolerance: float
    mode: str
    requested: str
    W0: float
    alpha_h: float
    gain_G: float
    budget_v_max: float
    budget_tolerance: float
    budget_refusal: str | None
    governor_level: float
    governor_tolerance: float
    governor_refusal: str | None

    @property
    def guaranteed_tolerance(self) -> float:
        """The EPS proved for the run of ``mode``."""
        return self.budget_tolerance if self.mode == "budget" else self.governor_tolerance

    def law(self, mode: str, gain: float, m_hat: int, v_certified: float, lam: float, eps: float) -> Law:
        """The :class:`Law` of ``mode`` (budget: the set-point law with v_max = budget_v_max / sqrt(m_hat), so that
        the elementwise clip keeps the 2-norm of v below budget_v_max; governor: v_sp clipped at
        v_max_certified / sqrt(m_hat))."""
        root = np.sqrt(m_hat)
        if mode == "budget":
            return Law("setpoint", gain, self.budget_v_max / root)
        return Law("governor", gain, v_certified / root, self.governor_level, GOVERNOR_RATE * (lam - eps))


def guaranteed_plan(tolerance: float, mode: str, W0: float, up: dict, gain: float | None = None) -> GuaranteedPlan:
    """Budget and governor of a guaranteed controller for a start with W(xi0, x0) = W0.

    Budget (eq. (9) with the uniform bound of Theorem 2, eqs. (8) and (38)): the largest v_max with
    sqrt(W0 e^(-(lambda - eps) t) / alpha_h) + G v_max <= EPS for all t >= 0; the left side is largest at t = 0,
    so v_max = (EPS - sqrt(W0 / alpha_h)) / G, capped by v_max_certified (the bound holds only there).  With
    disturbances (``concrete.disturbances``) every w in their box is admitted: v_max = (EPS - sqrt(W0 / alpha_h) -
    G_w ||w||_inf) / G, capped by the region's limit with w; the governor is refused (it cannot see w).  A fitted p's
    PDE residual (``bound.residual_term``) is spent the same way, before any v; the governor counts it in its
    condition (|L^T r(s)| + rho_bar)^2 / eps <= room.
    Governor: the level W_max = min(EPS^2 alpha_h, w0_max_certified), kept invariant (less GOVERNOR_MARGIN); it
    needs W0 <= W_max.

    Parameters
    ----------
    tolerance : float
        EPS.
    mode : str
        ``auto``, ``budget`` or ``governor``.
    W0 : float
        W(xi0, x0).
    up : dict
        The design's artefacts (``bound`` is read).
    gain : float, optional
        G to use instead of the bound stage's: G with dbar taken over the part of V a plan keeps to (a task's plan,
        :func:`ashc_cli.design.task_plan.plan_task`) [default: ``bound.gain``].

    Returns
    -------
    GuaranteedPlan

    Raises
    ------
    DesignError
        Naming ``simulate.tracking.abstract_controller.tolerance`` (exit 3), with the least tolerance that
        can be met, when the mode asked for (``auto``: either) cannot certify EPS from this start.
    """
    bd = up["bound"].values
    alpha_h, G = float(bd["alpha_h"]), float(bd["gain"]) if gain is None else float(gain)
    w0_max = float(bd.get("w0_max_certified", np.inf))
    v_cert = float(bd.get("v_max_certified", np.inf))
    start = float(np.sqrt(max(W0, 0.0) / alpha_h))          # sqrt(W0 / alpha_h), the first term of eq. (9) at t = 0
    # A spec with disturbances admits every w in disturbance_bounds: the bound's G_w ||w||_inf is spent before any v,
    # and the region's v limit is the one that keeps {W <= c} invariant with w (bound.v_max_certified_with_w).
    # A fitted p's PDE residual is a disturbance that is always there (bound.residual_term, docs/guaranteed.md).
    w_term = float(bd.get("disturbance_term", 0.0)) + float(bd.get("residual_term", 0.0))
    if "disturbance_term" in bd:
        v_cert = float(bd.get("v_max_certified_with_w", v_cert))
    start_w = start + w_term
    least = start_w * (1.0 + BUDGET_MARGIN)
    region = "" if not np.isfinite(w0_max) else f", W0 <= w0_max_certified = {w0_max:.6g}"
    budget_refusal = governor_refusal = None
    if W0 > w0_max:
        budget_refusal = governor_refusal = (f"W(xi0, x0) = {W0:.6g} is outside the region where the bound is certified (W0 <= {w0_max:.6g}): "
                                             "no tolerance is certified from this start")
    elif not tolerance > start_w:
        taken = f"the start alone takes sqrt(W0 / alpha_h) = {start:.6g}" if w_term == 0 else \
            f"the start and the disturbance take sqrt(W0 / alpha_h) + G_w ||w||_inf (+ p's residual term) = {start:.6g} + {w_term:.6g}"
        budget_refusal = (f"{taken} of the tolerance {tolerance:g} (W0 = {W0:.6g}, alpha_h = {alpha_h:.6g}), which leaves no v "
                          "(eq. (9) at t = 0)")
    elif not v_cert > 0:
        budget_refusal = (f"the region's v limit with the disturbance is {v_cert:.6g} (bound.v_max_certified_with_w): no v keeps the "
                          "certified region invariant against every w in disturbance_bounds")
    budget_v = min((tolerance - start_w) / G, v_cert) if budget_refusal is None else np.nan
    budget_tol = start_w + G * budget_v if budget_refusal is None else np.nan
    proved = min(tolerance**2 * alpha_h, w0_max)                # w <= proved gives |psi - y| <= sqrt(proved / alpha_h) <= EPS
    level = (1.0 - GOVERNOR_MARGIN) * proved
    if governor_refusal is None and "disturbance_term" in bd:
        governor_refusal = ("the governor keeps W below its level from the interface's own r(s), which cannot see the disturbance "
                            "e(x) w of concrete.disturbance_bounds (the budget mode counts it)")
    rho = float(bd.get("rho_bar", 0.0))
    if governor_refusal is None and rho > 0 and not rho**2 < float(bd["epsilon"]) * (float(bd["lambda"]) - float(bd["epsilon"])) * level:
        # at s = 0 the residual alone must fit: rho_bar^2 / eps < (lambda - eps) W_max
        governor_refusal = (f"the fitted p's PDE residual (rho_bar = {rho:.3g}) alone reaches the governor's level W_max = {level:.6g}: "
                            "the tolerance must exceed the bound's residual term")
    if governor_refusal is None and not W0 <= level:
        governor_refusal = (f"W(xi0, x0) = {W0:.6g} is above the level the governor keeps, W_max = {level:.6g} "
                            f"(tolerance^2 alpha_h less {GOVERNOR_MARGIN:g}{region})")
    chosen = mode
    if mode == "auto":
        # The governor allows every v the budget allows, and more (docs/guaranteed.md): it runs whenever it can.
        chosen = "governor" if governor_refusal is None else "budget"
    why = budget_refusal if chosen == "budget" else governor_refusal
    if why is not None:
        if W0 > w0_max:
            raise DesignError("simulate.tracking.x0", why, f"a start with W(xi0, x0) <= {w0_max:.6g} (bound.w0_max_certified)")
        raise DesignError("simulate.tracking.abstract_controller.tolerance", f"{tolerance:g} cannot be guaranteed ({chosen} mode): {why}",
                          f"a tolerance of at least {least:.6g} (sqrt(W0 / alpha_h) = {start:.6g} plus a margin), or a start nearer the manifold")
    return GuaranteedPlan(tolerance=float(tolerance), mode=chosen, requested=mode, W0=float(W0), alpha_h=alpha_h, gain_G=G,
                          budget_v_max=float(budget_v), budget_tolerance=float(budget_tol), budget_refusal=budget_refusal,
                          governor_level=float(level), governor_tolerance=float(np.sqrt(proved / alpha_h)), governor_refusal=governor_refusal)
