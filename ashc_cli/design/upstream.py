"""Functions of upstream artefacts that several stages read: p and dp/dxi from ``manifold.h5``, and the set
where m is certified from ``inverse.h5``.  Stages import these, never each other's modules."""

from __future__ import annotations

import numpy as np

from ashc_cli.design.artefacts import Artefact
from ashc_cli.errors import ArtefactError
from ashc_cli.problem.model import Model


def p_function(man: Artefact, model: Model):
    """p(xi) for numpy, like :func:`ashc_cli.problem.model.lambdify` (one array per abstract state, values (n, 1, ...)):
    the stored series when p was kept numeric, else p's formula compiled.

    Parameters
    ----------
    man : Artefact
        The manifold stage's artefact (series ``p``, else expression ``p``).
    model : Model
        The spec's systems (xi and the parameter values).

    Returns
    -------
    callable
        ``p(*xi)`` of one array per abstract state, returning shape (n, 1, ...).
    """
    return man.series["p"] if "p" in man.series else model.numeric(man.expr("p"), list(model.xi))


def dp_function(man: Artefact, model: Model):
    """dp/dxi(xi) for numpy (values (n, n_hat, ...)), as :func:`p_function`.

    Parameters
    ----------
    man : Artefact
        The manifold stage's artefact (series ``dp_dxi``, else expression ``dp_dxi``).
    model : Model
        The spec's systems (xi and the parameter values).

    Returns
    -------
    callable
        ``dp(*xi)`` of one array per abstract state, returning shape (n, n_hat, ...).
    """
    return man.series["dp_dxi"] if "dp_dxi" in man.series else model.numeric(man.expr("dp_dxi"), list(model.xi))


#: An output this far outside ``m_domain`` (times the width of the interval, at least 1) still counts as inside:
#: the ends are floating-point values of kappa at the ends of V.
DOMAIN_RTOL = 1e-9


def format_box(box: np.ndarray) -> str:
    """A box of outputs as ``[a, b]`` (one output) or ``[a, b] x [c, d]``.

    Parameters
    ----------
    box : ndarray (p, 2)
        One [lo, hi] row per output (anything reshaped to that).

    Returns
    -------
    str
        The intervals to 6 significant digits, joined by `` x ``.
    """
    return " x ".join(f"[{float(lo) + 0.0:.6g}, {float(hi) + 0.0:.6g}]" for lo, hi in np.asarray(box, dtype=float).reshape(-1, 2))


def certified_set(art: Artefact) -> tuple[np.ndarray, str, str]:
    """Where m (and b, c, built from it) may be evaluated: the outputs h(x) it is certified for.

    Parameters
    ----------
    art : Artefact
        The inverse stage's artefact.

    Returns
    -------
    box : ndarray, shape (p, 2)
        ``values/m_domain``: one [lo, hi] row per output.
    name : str
        The set's short name (``kappa(V)``, ``Y``, ...).
    meaning : str
        Why m is certified there.

    Raises
    ------
    ArtefactError
        If the artefact does not record the set (written by an older ashc).
    """
    if "m_domain" not in art.values:
        raise ArtefactError("inverse.h5", "records no m_domain (the outputs where m is certified): it was written by an older ashc",
                            "a rerun of the inverse stage (`ashc design SPEC --force`)")
    box = np.asarray(art.values["m_domain"], dtype=float).reshape(-1, 2)
    return box, str(art.meta.get("m_domain_set", "m_domain")), str(art.meta.get("m_domain", ""))


def outside_certified_set(box: np.ndarray, y: np.ndarray) -> bool:
    """Whether the output(s) y (shape (p,)) lie outside the box m_domain, beyond ``DOMAIN_RTOL``; NaN is outside.

    Parameters
    ----------
    box : ndarray (p, 2)
        ``values/m_domain`` of the inverse artefact (:func:`certified_set`).
    y : ndarray (p,)
        The output h(x).

    Returns
    -------
    bool
        True if some output is below lo or above hi by more than ``DOMAIN_RTOL`` times max(1, hi - lo), or is NaN.
    """
    box = np.asarray(box, dtype=float).reshape(-1, 2)
    y = np.asarray(y, dtype=float).reshape(-1)
    tol = DOMAIN_RTOL * np.maximum(1.0, box[:, 1] - box[:, 0])
    inside = (y >= box[:, 0] - tol) & (y <= box[:, 1] + tol)
    return not bool(np.all(inside))


def sample_box(model: Model, p_grid: np.ndarray) -> np.ndarray:
    """Where samples of X_y are drawn: ``concrete.state_box`` if given, else the manifold's box widened.

    Parameters
    ----------
    model : Model
        The spec's systems (``state_box`` is read).
    p_grid : ndarray (n, N)
        p on the grid of V (the manifold's ``p_grid``); without a state box each state's range is widened by its
        width plus 1 on both sides.

    Returns
    -------
    ndarray (n, 2)
        One [lo, hi] row per state.
    """
    if model.state_box is not None:
        return model.state_box
    return np.c_[p_grid.min(axis=1) - np.ptp(p_grid, axis=1) - 1.0, p_grid.max(axis=1) + np.ptp(p_grid, axis=1) + 1.0]
