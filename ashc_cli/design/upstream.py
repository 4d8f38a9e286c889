"""Functions of upstream artefacts that several stages read: p and dp/dxi from ``manifold.h5``, the set where m is
certified from ``inverse.h5``, and the reference states of levels (kappa(xi) = level on V).  Stages import these,
never each other's modules."""

from __future__ import annotations

from ashc_cli.design.solvers import cp
import numpy as np
import scipy.optimize as sopt
import sympy as sp

from ashc_cli.closedloop.terms import DesignTerms
from ashc_cli.design.artefacts import Artefact
from ashc_cli.errors import ArtefactError, DesignError
from ashc_cli.problem.grids import domain_grid
from ashc_cli.problem.expr import parse_expression
from ashc_cli.problem.model import TIME, Model


def theta_is_pointwise(model: Model) -> bool:
    """Whether ||L^T dp/dxi delta(xi)|| (theta with q = 0) bounds |L^T r| / |v| at every xi, state and factor the
    interface applies: q = 0; no channel-by-channel clipping of several inputs (one input, ``saturate: scale`` or
    ``false``), where the least-squares q never does worse than q = 0 and the factor enters affinely; or a feedback
    design, inside its region where nothing clips.  Otherwise (several inputs clipped channel by channel) theta of a
    clipping pattern can exceed it, and the bound stage's dbar is the sup over the patterns (the bound stage and the
    error-aware plan both read this).

    Parameters
    ----------
    model : Model

    Returns
    -------
    bool
    """
    itf = model.spec.interface
    return itf.q == "zero" or itf.saturate is not True or model.m == 1 or model.spec.stabilisability.feedback == "linear_gain"


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


# --- reference states: the least-norm xi in V with kappa(xi) = a level (simulate, tradeoff) -------------------


def reference_state(model: Model, plant: DesignTerms, level: np.ndarray, index: int, kappa: sp.Matrix, where: str | None = None) -> np.ndarray:
    """The least-norm xi in V with kappa(xi) = level.

    Affine kappa: the quadratic program min ||xi||^2 s.t. K xi + k0 = level, xi in V (cvxpy + Clarabel).
    Scalar abstraction: the roots of kappa - level on a fine grid of V, refined, the smallest kept.

    Parameters
    ----------
    model : Model
        The spec's systems (V fixed).
    plant : DesignTerms
        The design's compiled terms (``plant.kappa`` is read for a nonlinear kappa).
    level : ndarray (p,)
        The reference level.
    index : int
        The level's position in ``simulate.tracking.reference_levels`` (for the error message).
    kappa : sympy Matrix (p, 1)
        kappa(xi), the kappa artefact's formula.
    where : str, optional
        The spec field an error names (default ``simulate.tracking.reference_levels[index]``).

    Returns
    -------
    ndarray (n_hat,)

    Raises
    ------
    DesignError
        If kappa does not reach the level on V.
    """
    where = where or f"simulate.tracking.reference_levels[{index}]"
    if not any(e.free_symbols & set(model.xi) for e in kappa.jacobian(model.xi)):
        K = np.array(model.substitute(kappa.jacobian(model.xi)), dtype=float)
        k0 = np.array(model.substitute(kappa.xreplace({s: 0 for s in model.xi})), dtype=float).reshape(-1)
        xi = cp.Variable(model.n_hat)
        problem = cp.Problem(cp.Minimize(cp.sum_squares(xi)), [K @ xi + k0 == level, xi >= model.V[:, 0], xi <= model.V[:, 1]])
        problem.solve(solver=cp.CLARABEL)
        if xi.value is None or problem.status not in ("optimal", "optimal_inaccurate"):
            raise DesignError(where, f"level {level.tolist()} is not reached by kappa on V ({problem.status})", "levels inside kappa(V)")
        return np.asarray(xi.value, dtype=float)
    if model.n_hat != 1:
        return _reference_state_nonlinear(model, plant, level, where)
    lo, hi = model.V[0]
    grid = np.linspace(lo, hi, 20001)
    err = plant.kappa(grid)[0, 0] - level[0]
    roots = [grid[k] for k in np.flatnonzero(err == 0)]
    for k in np.flatnonzero(np.sign(err[:-1]) * np.sign(err[1:]) < 0):
        roots.append(sopt.brentq(lambda s: plant.kappa(s)[0, 0] - level[0], grid[k], grid[k + 1], xtol=1e-14))
    if not roots:
        k_lo, k_hi = float(np.min(err + level[0])), float(np.max(err + level[0]))
        raise DesignError(where, f"level {level[0]:g} is not reached by kappa on V (kappa(V) = [{k_lo:.6g}, {k_hi:.6g}])",
                          "levels inside kappa(V)")
    return np.array([min(roots, key=abs)])


def _reference_state_nonlinear(model: Model, plant: DesignTerms, level: np.ndarray, where: str) -> np.ndarray:
    """Several abstract states, nonlinear kappa: bounded least squares on kappa(xi) = level from the points
    of a coarse grid of V; of the exact solutions found, the least-norm one."""
    starts = domain_grid(model.V, 5 ** model.n_hat)
    bounds = (model.V[:, 0], model.V[:, 1])
    found = []
    for start in starts.T:
        fit = sopt.least_squares(lambda s: plant.kappa(*s)[:, 0] - level, start, bounds=bounds, xtol=1e-15, ftol=1e-15, gtol=1e-15)
        if np.abs(fit.fun).max() <= 1e-10 * max(1.0, np.abs(level).max()):
            found.append(fit.x)
    if not found:
        raise DesignError(where, f"level {level.tolist()} is not reached by kappa on V", "levels inside kappa(V)")
    return min(found, key=np.linalg.norm)


def reference_signal(model: Model):
    """The tracking scenario's reference signal r(t) for numpy (values (p, 1, N) for an array of t), parsed from
    ``simulate.tracking.reference`` (expressions in t and the parameters; the time signals triangle, square, step).

    Parameters
    ----------
    model : Model
        The spec's systems.

    Returns
    -------
    callable

    Raises
    ------
    SpecError
        If an expression does not parse or names anything but t and the parameters.
    """
    names = {**model.params, "t": TIME}
    texts = model.spec.simulate.tracking.reference_texts()
    r = sp.Matrix([parse_expression(text, names, f"simulate.tracking.reference[{i}]", signal=True) for i, text in enumerate(texts)])
    return model.numeric(r, [TIME])


def reference_sample_times(tr) -> np.ndarray:
    """The times k T at which a reference signal is sampled, one per held segment of the run.

    Parameters
    ----------
    tr : Tracking
        The spec's tracking scenario (T = ``tr.hold()``, and t_final).

    Returns
    -------
    ndarray
        0, T, 2 T, ... below t_final.
    """
    count = max(1, int(np.ceil(tr.t_final / tr.hold() - 1e-9)))
    return tr.hold() * np.arange(count)


def signal_levels(model: Model, plant: DesignTerms, kappa: sp.Matrix) -> tuple[list[np.ndarray], list[np.ndarray]]:
    """(levels, refs) of a reference signal: r(k T) and the reference state of each (:func:`reference_state`), held
    from k T to (k + 1) T (a zero-order hold, as a digital controller applies a reference).

    Parameters
    ----------
    model : Model
        The spec's systems (``simulate.tracking.reference``).
    plant : DesignTerms
        The design's compiled terms (kappa).
    kappa : sympy Matrix (p, 1)
        kappa(xi), the kappa artefact's formula.

    Returns
    -------
    levels, refs : list of ndarray (p,), list of ndarray (n_hat,)

    Raises
    ------
    DesignError
        If r is not finite at a sample, or a sample is out of kappa's reach on V (naming its time).
    """
    tr = model.spec.simulate.tracking
    times = reference_sample_times(tr)
    values = np.broadcast_to(reference_signal(model)(times)[:, 0, :], (model.p, times.size))
    if not np.all(np.isfinite(values)):
        k = int(np.argmax(~np.all(np.isfinite(values), axis=0)))
        raise DesignError("simulate.tracking.reference", f"r(t) is not finite at t = {times[k]:g} s", "a reference signal finite over the run")
    solved: dict[tuple, np.ndarray] = {}
    levels, refs = [], []
    for k, level in enumerate(values.T):
        key = tuple(level.tolist())
        if key not in solved:
            solved[key] = reference_state(model, plant, np.array(level), k, kappa, where=f"simulate.tracking.reference (at t = {times[k]:g} s)")
        levels.append(np.array(level))
        refs.append(solved[key])
    return levels, refs


def tracking_start(model: Model, plant: DesignTerms, up: dict[str, Artefact]) -> tuple[np.ndarray, np.ndarray, float, list[np.ndarray], list[np.ndarray]]:
    """The tracking run's start and references: (xi0, x0, W0 = W(xi0, x0), levels, xi_ref per level), W of eq. (35).

    Parameters
    ----------
    model : Model
        The spec's systems (``simulate.tracking``: xi0, x0, the reference levels).
    plant : DesignTerms
        The design's compiled terms (p and kappa).
    up : dict of str to Artefact
        The design's artefacts (``kappa`` and ``stabilise``'s M are read).

    Returns
    -------
    xi0, x0 : ndarray (n_hat,), (n,)
        The start; x0 = p(xi0) for ``x0: on_manifold``.
    W0 : float
        (p(xi0) - x0)^T M (p(xi0) - x0).
    levels, refs : list of ndarray (p,), list of ndarray (n_hat,)
        The reference levels and the reference state of each (:func:`reference_state`).

    Raises
    ------
    DesignError
        If xi0 is outside V or a level is out of kappa's reach.
    """
    tr = model.spec.simulate.tracking
    xi0 = np.array(tr.xi0, dtype=float)
    if model.V is not None and not np.all((model.V[:, 0] <= xi0) & (xi0 <= model.V[:, 1])):
        raise DesignError("simulate.tracking.xi0", f"xi0 = {xi0.tolist()} is outside V = {model.V.tolist()}", "xi0 in V")
    x0 = plant.p_map(*xi0)[:, 0] if tr.x0 == "on_manifold" else np.array(tr.x0, dtype=float)
    if tr.abstract_controller.kind == "signal":
        levels, refs = [np.ravel(plant.kappa(*xi0))], [xi0]      # v(t) drives xi: nothing is tracked (one segment)
    elif tr.reference is not None:
        levels, refs = signal_levels(model, plant, up["kappa"].expr("kappa"))
    else:
        levels = [np.atleast_1d(np.asarray(level, dtype=float)) for level in tr.level_values()]
        refs = [reference_state(model, plant, level, i, up["kappa"].expr("kappa")) for i, level in enumerate(levels)]
    M = np.asarray(up["stabilise"].value("M"))
    e0 = plant.p_map(*xi0)[:, 0] - x0
    return xi0, x0, float(e0 @ M @ e0), levels, refs
