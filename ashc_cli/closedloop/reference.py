"""The closed-loop laws in numpy, one point at a time: the set-point law and the guaranteed controller (its plan
from the bound, the budget and the governor) with the interface and its saturation.  The tests' oracle integrates them with solve_ivp; the compiled loops
(:mod:`ashc_cli.closedloop.tracking_core`, :mod:`ashc_cli.closedloop.governor`) are tested against them."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ashc_cli.closedloop.terms import DesignTerms
from ashc_cli.errors import DesignError
from ashc_cli.numerics.linalg import pinv
from ashc_cli.problem.model import apply_saturation


#: Bisection steps of the governor's search for s where the interface is not piecewise affine in s.
GOVERNOR_BISECTIONS = 60


#: Relative steps back from a root of the governor's quadratic tried before bisecting (rounding puts it a few
#: ulps either side of the boundary).
GOVERNOR_BACKOFF = (0.0, 1e-13, 1e-11)


#: Grid of s in [0, 1] searched first where the interface is not piecewise affine in s (saturate: scale, K e != 0).
GOVERNOR_GRID = 64


def tracking_law(plant: DesignTerms, xi: np.ndarray, x: np.ndarray, xi_ref: np.ndarray, gain: float, v_max: float,
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
    v = np.clip(pinv(delta) @ (gain * (xi_ref - xi) - phi[:, 0]), -v_max, v_max)
    feedback = plant.K @ (x - p[:, 0])   # k(x, p(xi), l(xi)) - l(xi) of eq. Interface (0 for identity feedback)
    u_nominal = l[:, 0] + feedback
    correction = feedback
    if q_kind == "least_squares":
        q = pinv(plant.L.T @ g) @ (plant.L.T @ dpd)   # argmin ||sqrt(M)(dp/dxi delta - g q)||, eq. egqLS
        correction = correction + q @ v
    u = apply_saturation(l[:, 0], correction, plant.U, saturate)
    return v, u, phi[:, 0] + delta @ v, f_bar[:, 0] + g @ u, dpd @ v - g @ (u - u_nominal)


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
    """

    kind: str
    gain: float
    v_max: float
    w_level: float = np.inf
    rate: float = 0.0


def interface_r(s: np.ndarray, L: np.ndarray, l: np.ndarray, feedback: np.ndarray, qv: np.ndarray, dv: np.ndarray,
                 g: np.ndarray, U: np.ndarray, saturate) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """u(s), r(s) and |L^T r(s)|^2 for v = s v_sp, at each s of an array (one point (xi, x)).

    u(s) = SAT(l + K e + s q v_sp) (the actual interface, eqs. Interface, egInterfaceSat) and
    r(s) = s dp/dxi delta v_sp - g (u(s) - l - K e) (eq. iota: what drives W in W' <= -(lambda - eps) W + |L^T r|^2 / eps).
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
    """What a guaranteed controller can certify for one run (eq. TrackConst, docs/guaranteed.md).

    Attributes
    ----------
    tolerance : float
        The spec's EPS.
    mode : str
        The mode that runs: ``budget`` or ``governor`` (``auto`` resolved).
    requested : str
        The spec's mode (``auto``, ``budget`` or ``governor``).
    W0, alpha_h, gain_G : float
        W(xi0, x0), alpha_h and the gain G of eq. egErrorBound.
    budget_v_max : float
        The largest |v| (2-norm) with sqrt(W0 / alpha_h) + G |v| <= EPS, capped by v_max_certified; NaN when
        none exists.
    budget_tolerance : float
        sqrt(W0 / alpha_h) + G budget_v_max: what the budget mode proves (<= EPS).
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


def guaranteed_plan(tolerance: float, mode: str, W0: float, up: dict) -> GuaranteedPlan:
    """Budget and governor of a guaranteed controller for a start with W(xi0, x0) = W0.

    Budget (eq. TrackConst with the uniform bound of Theorem ErrorBound, eq. egErrorBound): the largest v_max with
    sqrt(W0 e^(-(lambda - eps) t) / alpha_h) + G v_max <= EPS for all t >= 0; the left side is largest at t = 0,
    so v_max = (EPS - sqrt(W0 / alpha_h)) / G, capped by v_max_certified (the bound holds only there).
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
    alpha_h, G = float(bd["alpha_h"]), float(bd["gain"])
    w0_max = float(bd.get("w0_max_certified", np.inf))
    v_cert = float(bd.get("v_max_certified", np.inf))
    start = float(np.sqrt(max(W0, 0.0) / alpha_h))          # sqrt(W0 / alpha_h), the first term of eq. TrackConst at t = 0
    least = start * (1.0 + BUDGET_MARGIN)
    region = "" if not np.isfinite(w0_max) else f", W0 <= w0_max_certified = {w0_max:.6g}"
    budget_refusal = governor_refusal = None
    if W0 > w0_max:
        budget_refusal = governor_refusal = (f"W(xi0, x0) = {W0:.6g} is outside the region where the bound is certified (W0 <= {w0_max:.6g}): "
                                             "no tolerance is certified from this start")
    elif not tolerance > start:
        budget_refusal = (f"the start alone takes sqrt(W0 / alpha_h) = {start:.6g} of the tolerance {tolerance:g} (W0 = {W0:.6g}, "
                          f"alpha_h = {alpha_h:.6g}), which leaves no v (eq. TrackConst at t = 0)")
    budget_v = min((tolerance - start) / G, v_cert) if budget_refusal is None else np.nan
    budget_tol = start + G * budget_v if budget_refusal is None else np.nan
    proved = min(tolerance**2 * alpha_h, w0_max)                # w <= proved gives |psi - y| <= sqrt(proved / alpha_h) <= EPS
    level = (1.0 - GOVERNOR_MARGIN) * proved
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
