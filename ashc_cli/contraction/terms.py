"""The Jacobian df/dx over concrete.state_box x U, for f not affine in x: the matrices the LMI is imposed on.

For f not affine in x, V(x, z) = (x - z)^T M (x - z) decays at rate lambda along any pair of solutions that stay in
the (convex) state box if J^T M + M J <= -lambda M for every J = df/dx(s, u) with s in the box (the mean-value form
f(x, u) - f(z, u) = int_0^1 J(z + s (x - z), u) ds (x - z)).
"""

from __future__ import annotations

import itertools

import numpy as np
import sympy as sp

from .. import proofs
from ..errors import DesignError, SpecError
from ..grids import domain_grid, maximise_on_box
from ..model import Model, sparse_jacobian


#: At most this many Jacobian entries may vary over the state box (the polytope has 2^k vertices).
MAX_VARYING_ENTRIES = 12


RANGE_SAMPLES = 40000


#: Seconds the branch and bound may spend enclosing one end of one Jacobian entry's range (then the range is
#: only sampled, and the LMI row says so).
ENCLOSURE_TIME_BUDGET = 20.0


#: Relative width at which that branch and bound stops (the enclosure is rigorous at any width; a tighter one
#: only makes the LMI less conservative).
ENCLOSURE_RTOL = 1e-6


def refuse_jumps(model: Model) -> None:
    """Refuse an f with a jump (sign, square, step of a state) inside state_box x U: the Jacobian LMI's mean-value
    argument needs f Lipschitz there.  (abs, min and max are Lipschitz and handled by their generalised derivatives.)

    Raises
    ------
    DesignError
        Naming the field, the function and where its argument crosses the jump.
    """
    fields = [(f"concrete.f_bar[{i}]", e) for i, e in enumerate(model.f_bar)]
    fields += [(f"concrete.g[{i}][{j}]", model.g[i, j]) for i in range(model.n) for j in range(model.m)]
    proofs.refuse_jumps(model, fields, list(model.x) + list(model.u), np.r_[model.state_box, model.U],
                        "f is not Lipschitz on state_box x U, so no Jacobian LMI (eq. egLMI) can certify it",
                        "a smooth approximation of the jump", check="lmi_margin")


def jacobian_polytope(model: Model, J: sp.Matrix | None = None) -> tuple[sp.Matrix, list[np.ndarray], np.ndarray, dict]:
    """A polytope containing the Jacobian df/dx(x, u) for x in ``concrete.state_box`` and u in U.

    For f not affine in x, V(x, z) = (x - z)^T M (x - z) decays at rate lambda along any pair of solutions
    that stay in the (convex) state box if J^T M + M J <= -lambda M for every J = df/dx(s, u) with s in the
    box (the mean-value form f(x, u) - f(z, u) = int_0^1 J(z + s (x - z), u) ds (x - z)).  Each entry of J
    that varies is enclosed over box x U by ball arithmetic with branch and bound (:func:`proofs.range_on_box`:
    rigorous at any width, so a steep term such as tanh(50000 x) whose derivative peaks in a band 1e-4 wide is
    inside the range), and the LMI is imposed at the 2^k vertices of the box of entry ranges, which contains J.
    Where ball arithmetic cannot enclose an entry (or the enclosure is not finite), its range comes from a
    grid refined by bounded local searches, widened by 1e-9 relative: the LMI is then only *sampled*
    (``meta["ranges_proved"]`` is False) and ``ashc check`` says so.

    Returns
    -------
    J : sympy Matrix
        df/dx(x, u).
    A_list : list of ndarray
        The vertex matrices.
    ranges : ndarray, shape (k, 2)
        The range of each varying entry.
    meta : dict
        Which entries vary, how their ranges were found (``ranges_proved``), and the sampled ranges beside them.

    Raises
    ------
    SpecError
        Without ``concrete.state_box``.
    DesignError
        If more than ``MAX_VARYING_ENTRIES`` entries vary, or an entry is unbounded on the box.
    """
    if model.state_box is None:
        raise SpecError("concrete.state_box", "missing: f(x, u) is not affine in x, so the incremental LMI is imposed on the Jacobian over a box of states",
                        "one pair [lo, hi] per state (the region the design is certified on)")
    J = sparse_jacobian(model.f, model.x) if J is None else J
    args = list(model.x) + list(model.u)
    box = np.r_[model.state_box, model.U]
    varying = [(i, j) for (i, j), e in np.ndenumerate(np.array(J, dtype=object)) if e.free_symbols & set(args)]
    if len(varying) > MAX_VARYING_ENTRIES:
        raise DesignError("concrete", f"{len(varying)} Jacobian entries vary over the state box (at most {MAX_VARYING_ENTRIES}: the polytope has 2^k vertices)",
                          "fewer state-dependent terms, or f affine in x")
    pts = domain_grid(box, RANGE_SAMPLES)
    ranges, sampled, how = [], [], []
    for i, j in varying:
        name = f"df{i + 1}/d{model.x[j]}"
        fun = model.numeric([J[i, j]], args)
        vals = np.broadcast_to(fun(*pts)[0, 0], pts.shape[1])
        if not np.all(np.isfinite(vals)):
            bad = pts[:, int(np.argmax(~np.isfinite(vals)))]
            raise DesignError("concrete.state_box", f"{name} is not finite on the box (at {np.round(bad, 6).tolist()})", "a box on which f is C^1")
        hi, _ = maximise_on_box(pts, vals, lambda z, fun=fun: float(fun(*z)[0, 0]), box)
        neg_lo, _ = maximise_on_box(pts, -vals, lambda z, fun=fun: -float(fun(*z)[0, 0]), box)
        lo = -neg_lo
        sampled.append((lo, hi))
        enclosed = _enclose_entry(model, J[i, j], args, box)
        if enclosed is not None:
            ranges.append(enclosed)
            how.append("enclosed")
        else:
            pad = 1e-9 * max(1.0, abs(lo), abs(hi))
            ranges.append((lo - pad, hi + pad))
            how.append("sampled")
    J0 = np.array(model.substitute(J.xreplace({a: 0 for a in args})), dtype=float)
    A_list = []
    for corner in itertools.product(*ranges):
        A = J0.copy()
        for (i, j), value in zip(varying, corner):
            A[i, j] = value
        A_list.append(A)
    proved = all(h == "enclosed" for h in how)
    meta = {"jacobian_entries": [f"df{i + 1}/d{model.x[j]}" for i, j in varying],
            "state_box": model.state_box.tolist(), "ranges_proved": proved,
            "range_method": ("ball-arithmetic enclosure over box x U by branch and bound (rigorous)" if proved else
                             "enclosure where ball arithmetic reaches, else a grid of box x U refined by L-BFGS-B and widened 1e-9 (sampled): "
                             + ", ".join(f"{n} {h}" for n, h in zip((f'df{i + 1}/d{model.x[j]}' for i, j in varying), how))),
            "ranges_sampled": [list(r) for r in sampled]}
    return J, A_list, np.array(ranges, dtype=float).reshape(-1, 2), meta


def _enclose_entry(model: Model, entry: sp.Expr, args: list, box: np.ndarray) -> tuple[float, float] | None:
    """Proved bounds lo <= entry <= hi over the box (ball arithmetic, branch and bound), or None where ball
    arithmetic cannot enclose the entry or the enclosure is not finite."""
    try:
        fun = proofs.compile_claims(model, [entry], args)
    except proofs.interval.UnsupportedExpression:
        return None
    lo, ok_lo = proofs.inf_on_box(fun, box, rtol=ENCLOSURE_RTOL, time_budget=ENCLOSURE_TIME_BUDGET)
    hi, ok_hi, _ = proofs.sup_on_box(fun, box, rtol=ENCLOSURE_RTOL, time_budget=ENCLOSURE_TIME_BUDGET)
    return (lo, hi) if ok_lo and ok_hi else None


def jacobian_samples(model: Model, J: sp.Matrix, count: int = 2000, seed: int = 2) -> tuple[list[np.ndarray], np.ndarray]:
    """df/dx at random points of state_box x U (the numpy re-check of the Jacobian LMI), and the points (rows of (x, u))."""
    rng = np.random.default_rng(seed)
    box = np.r_[model.state_box, model.U]
    pts = rng.uniform(box[:, 0:1], box[:, 1:2], size=(len(box), count))
    values = np.broadcast_to(model.numeric(J, list(model.x) + list(model.u))(*pts), J.shape + (count,))
    return list(np.moveaxis(values, -1, 0)), pts.T

