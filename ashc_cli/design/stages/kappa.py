"""Stage 3: the abstract output map kappa = h o p (eq. (14b)).

kappa(xi) = h(p(xi)) makes the abstract system's output equal the concrete one on the manifold x = p(xi).
For the Cuk converter this is eq. (32).  The stage stores kappa, its values on V (Fig. 5) and
checks that it is finite there.  When the manifold stage kept p numeric (a Chebyshev series) and h(x) = C x,
kappa = C p is kept as a series too, without building p's formula; with another h and p a series in several abstract
states, kappa is a series of its own fitted to h(p) (:func:`_fit_composition`, checked as ``kappa_fit``).
"""

from __future__ import annotations

import numpy as np
import sympy as sp

from ashc_cli.numerics import chebyshev, proofs
from ashc_cli.design.artefacts import Artefact, Check
from ashc_cli.errors import NumericalError
from ashc_cli.problem.model import Model, tidy

NAME = "kappa"
UPSTREAM = ("manifold",)


def run(model: Model, upstream: dict[str, Artefact]) -> Artefact:
    """Compose kappa = h o p (eq. (14b)) and tabulate it on V.

    Parameters
    ----------
    model : Model
        The spec's systems (V fixed).
    upstream : dict of str to Artefact
        The manifold artefact (p, xi_grid and V are read).

    Returns
    -------
    Artefact
        Expressions kappa (p x 1) and dkappa_dxi (p x n_hat); values xi_grid, kappa_grid, kappa_range.

    Raises
    ------
    NumericalError
        If kappa is not finite somewhere on the grid of V.
    """
    man = upstream["manifold"]
    if model.C is None and model.state_box is not None:
        # A jump of h inside the box breaks Assumption 1 before anything is built on h (the inverse stage would
        # meet it as a failure of condition (ii)).
        proofs.refuse_jumps(model, [(f"concrete.h[{i}]", e) for i, e in enumerate(model.h)], list(model.x), model.state_box,
                            "h is not Lipschitz on concrete.state_box (Assumption 1), so alpha_h does not exist",
                            "a continuous output map", check="h_lipschitz")
    grid = np.asarray(man.value("xi_grid"))
    series = man.series["p"].left(model.C) if "p" in man.series and model.C is not None else None
    fit_check = None
    if series is None and isinstance(man.series.get("p"), chebyshev.Series) and len(man.series["p"].box) > 1:
        series, fit_check = _fit_composition(model, man, grid, float(man.meta["residual_rtol"]))
    if series is not None:
        # p kept numeric and h = C x: kappa = C p is a series too (its formula has one row per output, not n).
        kappa_grid = series.at(grid)[:, 0, :]
    else:
        kappa = tidy(model.h.xreplace(dict(zip(model.x, man.expr("p")))), lambda e: sp.factor(sp.simplify(e)))
        dkappa = kappa.jacobian(model.xi)
        kappa_grid = model.numeric(kappa, list(model.xi))(*grid)[:, 0, :]
    finite = bool(np.all(np.isfinite(kappa_grid)))
    if not finite:
        bad = grid[:, ~np.all(np.isfinite(kappa_grid), axis=0)][:, 0]
        raise NumericalError(NAME, f"kappa = h(p(xi)) is not finite at xi = {bad.tolist()}", "kappa finite on V")
    art = Artefact(stage=NAME, meta={"grid_points": int(grid.shape[1])})
    if series is not None:
        art.set_series("kappa", series, model.xi)
        art.set_series("dkappa_dxi", series.jacobian(), model.xi)
        kappa = art.expr("kappa")
    else:
        art.exprs.update({"kappa": kappa, "dkappa_dxi": dkappa})
    art.values.update({"xi_grid": grid, "kappa_grid": kappa_grid,
                       "kappa_range": np.c_[kappa_grid.min(axis=1), kappa_grid.max(axis=1)]})
    if series is not None:   # how far kappa's formula (read by simulate, eval) is from the series (round-off)
        art.values["kappa_formula_deviation"] = float(np.abs(series.formula_at(grid)[:, 0, :] - kappa_grid).max())
    if fit_check is not None:
        art.checks["kappa_fit"] = fit_check
    how = "ball arithmetic"
    if series is not None and len(series.box) > 1:
        # |T_k| <= 1 on V: the coefficients bound the series (and its formula's clipped cosines) without a box search
        bound, how = series.abs_bound(), "the sum of the series' |coefficients|"
    else:
        bound = _prove_finite(model, kappa, np.asarray(man.value("V"), dtype=float), small=series is not None)
    if np.isfinite(bound):
        art.checks["kappa_finite"] = Check(bound, True, f"proved bound of |kappa| on V ({how}: finite)", proofs.PROVED)
    else:
        art.checks["kappa_finite"] = Check(float(np.abs(kappa_grid).max()), finite, "largest |kappa| on the grid of V (finite)")
    return art


#: A fitted kappa = h(p) (p a series of several variables, h not linear) is fitted until its largest error on an
#: independent grid of V is below this fraction of the manifold's tolerance, relative to max(1, |kappa|) (or stops
#: improving; the check then judges it against the tolerance itself).
KAPPA_FIT_FRACTION = 1e-3
#: Degrees tried per axis above p's: p's, then in steps of this, up to three times p's.
KAPPA_FIT_STEP = 8


def _fit_composition(model: Model, man: Artefact, grid: np.ndarray, tolerance: float) -> tuple[chebyshev.Series, Check]:
    """kappa = h(p) for p a series of several abstract states and an h that is not linear: a Chebyshev series of
    its own on V, interpolating h(p(xi)) at Chebyshev nodes, and the check of that fit.

    Not h composed with p's formula: sympy simplified that for 80 s at degree 36 in two variables and its text filled
    the artefact.  The series' degree per axis is raised from p's until its error against h(p) on an independent
    grid meets ``KAPPA_FIT_FRACTION`` of ``tolerance`` (or stops improving); the check passes where that error is within the manifold's
    own tolerance (``tolerance``, relative), the accuracy p itself is claimed to.
    """
    p = man.series["p"]
    h = model.numeric(model.h, list(model.x))

    def composed(z: np.ndarray) -> np.ndarray:
        return np.array(np.broadcast_to(h(*p.at(z)[:, 0, :])[:, 0], (model.p, z.shape[1])))

    exact = composed(grid)
    scale = max(1.0, float(np.abs(exact).max()))
    best = None
    for degree in range(p.degree, 3 * p.degree + 1, KAPPA_FIT_STEP):
        z = chebyshev.nodes(p.box, degree + 1)
        fitted = chebyshev.Series.column(chebyshev.fit(composed(z), p.box, z, degree), p.box)
        error = float(np.abs(fitted.at(grid)[:, 0, :] - exact).max())
        if best is not None and error > best[1] / 2:
            break   # stopped improving: keep the better fit
        best = (fitted, error)
        if error <= KAPPA_FIT_FRACTION * tolerance * scale:
            break
    fitted, error = best
    return fitted, Check(error, error <= tolerance * scale, f"max over a {grid.shape[1]}-point grid of V of |kappa - h(p)| for kappa fitted as a Chebyshev "
                         f"series of degree {fitted.degree} (h is not linear; within {tolerance:g} x max(1, |kappa|), the manifold's tolerance)")


def _prove_finite(model: Model, kappa: sp.Matrix, V: np.ndarray, small: bool = False) -> float:
    """A proved upper bound of max_i |kappa_i| over V (inf where ball arithmetic cannot bound it).

    Skipped above ``proofs.MAX_PROOF_STATES`` states, where h(p) can be a large formula, unless ``small``
    (kappa the formula of a series, one polynomial per output whatever n).
    """
    if model.n > proofs.MAX_PROOF_STATES and not small:
        return np.inf
    try:
        f = proofs.compile_claims(model, list(kappa), list(model.xi))
    except proofs.interval.UnsupportedExpression:
        return np.inf
    worst = 0.0
    for i in range(len(kappa)):
        lo, hi, ok = proofs.range_on_box(f, V, index=i, rtol=1e-3)
        if not ok:
            return np.inf
        worst = max(worst, abs(lo), abs(hi))
    return float(worst)


def summarise(art: Artefact) -> dict:
    """Headline numbers for ``ashc summary``.

    Parameters
    ----------
    art : Artefact
        The kappa stage's artefact.

    Returns
    -------
    dict
        ``kappa`` (one formula per output, as text) and ``range_on_V`` (kappa_range, one [lo, hi] per output).
    """
    return {"kappa": [str(e) for e in art.exprs["kappa"]], "range_on_V": np.asarray(art.values["kappa_range"]).tolist()}


def headline(art: Artefact) -> str:
    """One progress line.

    Parameters
    ----------
    art : Artefact
        The kappa stage's artefact.

    Returns
    -------
    str
        kappa(V): kappa_range rounded to 4 decimals.
    """
    return f"kappa(V) = {np.round(np.asarray(art.values['kappa_range']), 4).tolist()}"
