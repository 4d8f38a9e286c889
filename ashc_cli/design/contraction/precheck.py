"""Before any LMI: can a rate lambda > 0 exist at all?  A refutation on sampled states, in seconds.

Eq. (28) with one M at the vertices of the term polytope implies it at every true Jacobian df/dx(x, u) of
state_box x U (they lie in the polytope's hull).  So one point of the box where df/dx has an eigenvalue s with
Re s >= 0 refutes every M and every lambda > 0: x^* (A^T M + M A + lambda M) x = (2 Re s + lambda) x^* M x > 0 for its
eigenvector x.  With ``feedback: linear_gain`` (x' = f_bar(x) + B u, B constant) the closed loop is A + B K, and a mode
s with Re s >= -lambda / 2 that B cannot reach (Popov-Belevitch-Hautus: rank [A - s I, B] < n) stays in A + B K for every
K.  The points are seeded samples of the box (real states, never a corner of independently taken term ranges), so the
refusal names a state the plant can be in, and comes before the enclosures and the SDP, which may take minutes on
such a plant.  Not finding such a point proves nothing; the LMI then decides.
"""

from __future__ import annotations

import dataclasses

import numpy as np

from ashc_cli.design.contraction.terms import jacobian_samples
from ashc_cli.errors import DesignError
from ashc_cli.problem.influence import output_cone
from ashc_cli.problem.model import Model

__all__ = ["PRECHECK_POINTS", "refute_rate"]

#: Seeded random points of state_box x U at which df/dx is examined (besides the centre and the centre with one
#: coordinate at an end of its range or at 0).
PRECHECK_POINTS = 256
#: Above this many states the precheck is skipped (an eigenvalue problem per point).
MAX_PRECHECK_STATES = 64


def refute_rate(model: Model, J, lam: float, choices: str = "") -> None:
    """Refuse, naming the state, a plant no M (or, with linear_gain, no K) can make contract at rate ``lam``.

    Parameters
    ----------
    model : Model
        The spec's systems (state_box, U, the feedback kind).
    J : sympy Matrix (n, n)
        df/dx(x, u).
    lam : float
        The decay rate asked (0 for ``maximise``: any positive rate).
    choices : str
        The other choices the tool accepts for this plant, appended to the hint (", or feedback: linear_gain ...").

    Raises
    ------
    DesignError
        At the sampled point whose refuting mode is worst (largest real part).
    """
    if model.n > MAX_PRECHECK_STATES:
        return
    if model.state_box is None:
        if any(e.free_symbols & set(model.x) for e in J):
            return                      # df/dx reads x and there is no box to sample (the stage refuses that itself)
        model = dataclasses.replace(model, state_box=np.zeros((model.n, 2)))     # df/dx is the same at every x
    samples, points = jacobian_samples(model, J, count=PRECHECK_POINTS, seed=7, points=_special_points(np.r_[model.state_box, model.U]))
    linear_gain = model.spec.stabilisability.feedback == "linear_gain"
    B = np.asarray(model.substitute(model.g), dtype=float) if linear_gain else None
    worst = None
    for A, point in zip(samples, points):
        if not np.all(np.isfinite(A)):
            continue
        eig = np.linalg.eigvals(A)
        bad = [s for s in eig if s.real >= (-lam / 2 if linear_gain else 0.0) and (not linear_gain or _unreachable(A, B, s))]
        if bad:
            s = max(bad, key=lambda z: z.real)
            if worst is None or s.real > worst[0].real:
                worst = (s, point, A)
    if worst is None:
        return
    s, point, A = worst
    n, reads = model.n, set().union(*(e.free_symbols for e in J))
    on_x, on_u = bool(reads & set(model.x)), bool(reads & set(model.u))
    parts = ([f"x = [{', '.join(f'{v:.4g}' for v in point[:n])}]"] if on_x else []) + ([f"u = [{', '.join(f'{v:.4g}' for v in point[n:])}]"] if on_u else [])
    at = ", ".join(parts) if parts else "every state (df/dx is constant)"
    leave = " (a state box that leaves this point out)" if on_x else ""
    seen = f"(found among {len(points)} sampled points of state_box x U, before any LMI){_mode_states(model, A, s)}"
    if linear_gain:
        raise DesignError("stabilisability.feedback", f"no gain K makes the plant contract at lambda = {lam:g}: at {at} the mode s = {_text(s)} of "
                          f"df/dx (Re s >= -lambda/2 = {-lam / 2:.4g}) is not reachable from the inputs (rank [A - s I, B] < {n}: "
                          f"the linearisation is not stabilisable there) {seen}",
                          f"a plant whose linearisation is stabilisable at every point of the state box{leave}"
                          + (f", or decay_rate below {-2 * s.real:.4g}" if s.real < 0 else "") + choices, check="lmi_margin")
    raise DesignError("stabilisability", f"no M certifies any decay rate lambda > 0 (eq. (28)): at {at} df/dx has the eigenvalue "
                      f"{_text(s)}, real part >= 0, so the plant does not contract there {seen}",
                      f"a plant that is incrementally stable on the set{leave}{choices}", check="lmi_margin")


def _mode_states(model: Model, A: np.ndarray, s: complex) -> str:
    """Where the mode s of A lives (the states of its eigenvector within 10% of the largest entry), and whether they
    can influence y at all (the output's cone, :func:`ashc_cli.problem.influence.output_cone`)."""
    eig, vec = np.linalg.eig(A)
    v = np.abs(vec[:, int(np.argmin(np.abs(eig - s)))])
    where = [k for k in range(model.n) if v[k] >= 0.1 * v.max()]
    names = ", ".join(str(model.x[k]) for k in where)
    outside = output_cone(model)[1]
    if set(where) <= set(outside):
        gone = ", ".join(str(model.x[k]) for k in outside)
        return (f"; the mode lives in {names}, which cannot influence y (no path of df/dx leads from them to h; the states outside "
                f"the output's cone are {gone}): leave them out of concrete.states, since the design certifies every state")
    return f"; the mode lives in {names}"


def _special_points(box: np.ndarray) -> np.ndarray:
    """The centre of the box, and the centre with one coordinate moved to its lower end, upper end or 0 (where 0 is
    inside): controllability is often lost on a thin set (a speed of 0), which random points never hit."""
    centre = box.mean(axis=1)
    rows = [centre]
    for k, (lo, hi) in enumerate(box):
        for value in (lo, hi) + ((0.0,) if lo < 0.0 < hi else ()):
            row = centre.copy()
            row[k] = value
            rows.append(row)
    return np.array(rows)


def _unreachable(A: np.ndarray, B: np.ndarray, s: complex) -> bool:
    """Whether the mode s of A is uncontrollable through B (PBH: [A - s I, B] loses rank, relative to its size)."""
    n = A.shape[0]
    pbh = np.hstack([A - s * np.eye(n), B.astype(complex)])
    sv = np.linalg.svd(pbh, compute_uv=False)
    return bool(sv[-1] <= 1e-9 * max(1.0, sv[0]))


def _text(s: complex) -> str:
    return f"{s.real:.4g}" if abs(s.imag) <= 1e-12 * max(1.0, abs(s)) else f"{s.real:.4g} {'+' if s.imag >= 0 else '-'} {abs(s.imag):.4g}i"
