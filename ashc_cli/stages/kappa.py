"""Stage 3: the abstract output map kappa = h o p (eq. SimuDesignCond2).

kappa(xi) = h(p(xi)) makes the abstract system's output equal the concrete one on the manifold x = p(xi).
For the Cuk converter this is eq. egKappa.  The stage stores kappa, its values on V (Fig. kappa_xi) and
checks that it is finite there.
"""

from __future__ import annotations

import numpy as np
import sympy as sp

from .. import proofs
from ..artefacts import Artefact, Check
from ..errors import NumericalError
from ..model import Model, tidy

NAME = "kappa"
UPSTREAM = ("manifold",)


def run(model: Model, upstream: dict[str, Artefact]) -> Artefact:
    """Compose kappa = h o p and tabulate it on V.

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
    p = man.expr("p")
    kappa = tidy(model.h.xreplace(dict(zip(model.x, p))), lambda e: sp.factor(sp.simplify(e)))
    dkappa = kappa.jacobian(model.xi)
    grid = np.asarray(man.value("xi_grid"))
    kappa_grid = model.numeric(kappa, list(model.xi))(*grid)[:, 0, :]
    finite = bool(np.all(np.isfinite(kappa_grid)))
    if not finite:
        bad = grid[:, ~np.all(np.isfinite(kappa_grid), axis=0)][:, 0]
        raise NumericalError(NAME, f"kappa = h(p(xi)) is not finite at xi = {bad.tolist()}", "kappa finite on V")
    art = Artefact(stage=NAME, meta={"grid_points": int(grid.shape[1])})
    art.exprs.update({"kappa": kappa, "dkappa_dxi": dkappa})
    art.values.update({"xi_grid": grid, "kappa_grid": kappa_grid,
                       "kappa_range": np.c_[kappa_grid.min(axis=1), kappa_grid.max(axis=1)]})
    bound = prove_finite(model, kappa, np.asarray(man.value("V"), dtype=float))
    if np.isfinite(bound):
        art.checks["kappa_finite"] = Check(bound, True, "proved bound of |kappa| on V (ball arithmetic: finite)", proofs.PROVED)
    else:
        art.checks["kappa_finite"] = Check(float(np.abs(kappa_grid).max()), finite, "largest |kappa| on the grid of V (finite)")
    return art


def prove_finite(model: Model, kappa: sp.Matrix, V: np.ndarray) -> float:
    """A proved upper bound of max_i |kappa_i| over V (inf where ball arithmetic cannot bound it)."""
    if model.n > proofs.MAX_PROOF_STATES:
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
    """Headline numbers for ``ashc summary``."""
    return {"kappa": [str(e) for e in art.exprs["kappa"]], "range_on_V": np.asarray(art.values["kappa_range"]).tolist()}


def headline(art: Artefact) -> str:
    """One progress line."""
    return f"kappa(V) = {np.round(np.asarray(art.values['kappa_range']), 4).tolist()}"
