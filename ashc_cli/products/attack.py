"""Attacks on what a design only *sampled*: counter-examples to its certificate rows, not to its bound.

``ashc falsify`` searches closed-loop runs for a violation of the bound.  A row that was checked on samples
only (the verdict "holds on samples only") can be false between the samples; a run may never meet the place
where it fails (a band 1e-4 wide, a second equilibrium the runs do not visit).  These searches go there
directly:

* :func:`lmi_counterexample`: a point (x, u) of state_box x U where the incremental LMI of eq. (28) fails,
  lambda_max(J^T M + M J + lambda M) > 0 with J = df/dx (+ B K), by bounded local optimisation of that margin from
  many starts, seeded where ball-arithmetic branch and bound finds each Jacobian entry largest and smallest;
* :func:`second_equilibrium`: two distinct equilibria of the frozen-input plant f(x, u) = 0 in the state box
  for the same u, which no contraction on the box allows (a multistart Newton search over inputs of U and of
  l(V));
* :func:`lipschitz_counterexample`: a state where ||dh/dx||_2 exceeds the L_h that alpha_h was built on.

Each returns a counter-example (a dict with its coordinates and what it breaks) or None; :func:`attack` runs
those whose row is sampled.
"""

from __future__ import annotations

import numpy as np
import scipy.optimize as sopt

from ashc_cli.numerics import proofs
from ashc_cli.design.artefacts import Artefact
from ashc_cli.problem.grids import domain_grid
from ashc_cli.problem.model import Model, sparse_jacobian

__all__ = ["attack", "lmi_counterexample", "second_equilibrium", "lipschitz_counterexample"]

#: Random starts of the local searches (besides the branch-and-bound seeds and the grid's best points).
STARTS = 256
#: Local searches run from the best of the starts.
LOCAL_SEARCHES = 24
#: Boxes the branch and bound may enclose locating each Jacobian entry's extremes (seeds only: any point helps;
#: a count, not seconds, so the attack finds the same points on any machine).
SEED_BOXES = 10000
#: Inputs u at which the frozen plant's equilibria are sought, per axis of U (and as many points of V through l).
INPUTS_PER_AXIS = 41


def _rng(seed: int = 0) -> np.random.Generator:
    return np.random.default_rng(seed)


def _closed_loop_jacobian(model: Model, arts: dict[str, Artefact]):
    """(x, u) -> df/dx + g K at a point: the matrix the LMI of eq. (28) is imposed on (K = 0 without feedback)."""
    J = sparse_jacobian(model.f, model.x)
    fun = model.numeric(J, list(model.x) + list(model.u))
    K = np.asarray(arts["stabilise"].values.get("K", np.zeros((model.m, model.n))), dtype=float).reshape(model.m, model.n)
    BK = 0.0
    if np.any(K):
        B = np.asarray(model.numeric(model.g, list(model.x))(*np.zeros(model.n)), dtype=float).reshape(model.n, model.m)
        BK = B @ K

    def at(z: np.ndarray) -> np.ndarray:
        return np.asarray(fun(*z), dtype=float).reshape(model.n, model.n) + BK

    return J, at


def lmi_counterexample(model: Model, arts: dict[str, Artefact], seed: int = 0) -> dict | None:
    """A point of state_box x U (or of U, for f affine in x) where eq. (28) fails for the design's M and lambda.

    Parameters
    ----------
    model : Model
        The spec's systems (f, g, ``state_box``, U).
    arts : dict of str to Artefact
        Artefacts by stage; ``stabilise`` is read (``M``, ``lambda``, and ``K`` when the feedback is linear).
    seed : int
        Seed of the random starts.

    Returns
    -------
    dict or None
        ``kind`` "lmi", ``x``, ``u``, ``margin`` (> 0: the largest eigenvalue of J^T M + M J + lambda M there)
        and ``relative_margin`` (over ||M||), or None if every search found the LMI to hold.
    """
    st = arts["stabilise"]
    M = np.asarray(st.values["M"], dtype=float)
    lam = float(st.values["lambda"])
    box = np.r_[model.state_box, model.U] if model.state_box is not None else np.r_[np.zeros((model.n, 2)), model.U]
    J, at = _closed_loop_jacobian(model, arts)
    scale = float(np.linalg.eigvalsh(M).max())

    def margin(z: np.ndarray) -> float:
        A = at(z)
        if not np.all(np.isfinite(A)):
            return -np.inf
        return float(np.linalg.eigvalsh(A.T @ M + M @ A + lam * M).max())

    rng = _rng(seed)
    starts = [rng.uniform(box[:, 0], box[:, 1]) for _ in range(STARTS)]
    starts += list(np.array(np.meshgrid(*box, indexing="ij")).reshape(len(box), -1).T) if len(box) <= 10 else []
    starts += _extremes(model, list(J), list(model.x) + list(model.u), box)
    values = np.array([margin(z) for z in starts])
    best = int(np.argmax(values))
    best_z, best_m = np.asarray(starts[best], dtype=float), float(values[best])
    for k in np.argsort(values)[::-1][:LOCAL_SEARCHES]:
        res = sopt.minimize(lambda z: -margin(z), np.asarray(starts[k], dtype=float), method="L-BFGS-B", bounds=[tuple(b) for b in box])
        if np.isfinite(res.fun) and -res.fun > best_m:
            best_z, best_m = np.asarray(res.x, dtype=float), float(-res.fun)
    if not best_m > 1e-12 * scale:
        return None
    return {"kind": "lmi", "x": best_z[:model.n].tolist(), "u": best_z[model.n:].tolist(), "margin": best_m, "relative_margin": best_m / scale,
            "lambda": lam, "breaks": "stabilisability certificate (LMI margin)"}


def _extremes(model: Model, exprs, args: list, box: np.ndarray) -> list[np.ndarray]:
    """Where branch and bound finds each expression that varies largest and smallest (seeds for the searches: a
    steep term's derivative peaks in a narrow band that random starts miss)."""
    from ashc_cli.numerics import boxsearch

    seeds = []
    for e in exprs:
        if not e.free_symbols & set(args):
            continue
        try:
            fun = proofs.compile_claims(model, [e], args)
        except proofs.interval.UnsupportedExpression:
            continue
        for search in (boxsearch.sup_on_box, boxsearch.inf_on_box):
            res = search(fun, box, rtol=1e-9, max_boxes=SEED_BOXES)
            point = getattr(res, "argmax", getattr(res, "argmin", None))
            if point is not None and np.all(np.isfinite(point)):
                seeds.append(np.asarray(point, dtype=float))
    return seeds


def _inputs(model: Model) -> np.ndarray:
    """The inputs u (rows) at which equilibria are sought: a grid of U and l(xi) on a grid of V."""
    per_axis = max(3, int(round(INPUTS_PER_AXIS ** (1.0 / model.m)))) if model.m <= 3 else 3
    us = [np.array(u) for u in np.array(np.meshgrid(*[np.linspace(lo, hi, per_axis) for lo, hi in model.U], indexing="ij")).reshape(model.m, -1).T]
    if model.V is not None:
        grid = domain_grid(model.V, INPUTS_PER_AXIS)
        ls = np.asarray(model.numeric(model.l, list(model.xi))(*grid), dtype=float)[:, 0, :]
        us += [ls[:, k] for k in range(ls.shape[1])]
    return np.array(us)


def second_equilibrium(model: Model, arts: dict[str, Artefact], seed: int = 0, starts: int = 24) -> dict | None:
    """Two distinct equilibria x_a != x_b of x' = f(x, u) in the state box for one u in U.

    Contraction at a rate lambda > 0 on a convex box makes the equilibrium for a frozen input unique (V(x_a, x_b)
    would have to decay and stay constant), so two of them refute the certificate, whatever the samples said.

    Parameters
    ----------
    model : Model
        The spec's systems (f, ``state_box``, U, and l and V for the inputs l(xi)).
    arts : dict of str to Artefact
        Artefacts by stage (not read; the signature of every attack).
    seed : int
        The random starts are drawn with seed ``seed + 1``.
    starts : int
        Newton (``hybr``) starts per input u.

    Returns
    -------
    dict or None
        ``kind`` "second_equilibrium", ``u``, ``x`` and ``x_other`` (both with |f| <= 1e-9 relative), ``distance``;
        None without a ``state_box`` or when no u has two.
    """
    if model.state_box is None:
        return None
    box = model.state_box
    f = model.numeric(model.f, list(model.x) + list(model.u))
    Jf = model.numeric(sparse_jacobian(model.f, model.x), list(model.x) + list(model.u))
    width = np.maximum(np.ptp(box, axis=1), 1e-12)
    rng = _rng(seed + 1)
    for u in _inputs(model):
        roots = []
        for _ in range(starts):
            x0 = rng.uniform(box[:, 0], box[:, 1])
            sol = sopt.root(lambda x: np.asarray(f(*x, *u), dtype=float).reshape(-1), x0,
                            jac=lambda x: np.asarray(Jf(*x, *u), dtype=float).reshape(model.n, model.n), method="hybr")
            x = np.asarray(sol.x, dtype=float)
            if not (sol.success and np.all(x >= box[:, 0]) and np.all(x <= box[:, 1])):
                continue
            size = max(1.0, float(np.abs(np.asarray(f(*x, *u), dtype=float)).max()), float(np.abs(x).max()))
            if float(np.abs(np.asarray(f(*x, *u), dtype=float)).max()) > 1e-9 * size:
                continue
            for r in roots:
                if np.max(np.abs(r - x) / width) > 1e-6:
                    return {"kind": "second_equilibrium", "u": list(map(float, u)), "x": r.tolist(), "x_other": x.tolist(),
                            "distance": float(np.linalg.norm(r - x)), "breaks": "stabilisability certificate (LMI margin)"}
            roots.append(x)
    return None


def lipschitz_counterexample(model: Model, arts: dict[str, Artefact], seed: int = 0) -> dict | None:
    """A state of the box where ||dh/dx||_2 exceeds the L_h of the design (alpha_h = lambda_min(M) / L_h^2 is then too large).

    Parameters
    ----------
    model : Model
        The spec's systems (h, ``state_box``).
    arts : dict of str to Artefact
        Artefacts by stage; ``bound`` is read (``lipschitz_h``).
    seed : int
        The random starts are drawn with seed ``seed + 2``.

    Returns
    -------
    dict or None
        ``kind`` "lipschitz", ``x``, ``norm`` (||dh/dx(x)||_2), ``L_h``; None for a linear h (L_h = ||C||_2 is exact),
        without a ``state_box``, or when no state exceeds L_h (1 + 1e-9).
    """
    if model.C is not None or model.state_box is None:
        return None
    L_h = float(arts["bound"].values["lipschitz_h"])
    box = model.state_box
    jac = sparse_jacobian(model.h, model.x)
    fun = model.numeric(jac, list(model.x))

    def norm(x: np.ndarray) -> float:
        return float(np.linalg.norm(np.asarray(fun(*x), dtype=float).reshape(model.p, model.n), 2))

    rng = _rng(seed + 2)
    starts = [rng.uniform(box[:, 0], box[:, 1]) for _ in range(STARTS)] + _extremes(model, list(jac), list(model.x), box)
    values = np.array([norm(x) for x in starts])
    best = int(np.argmax(values))
    best_x, best_v = np.asarray(starts[best], dtype=float), float(values[best])
    for k in np.argsort(values)[::-1][:LOCAL_SEARCHES]:
        res = sopt.minimize(lambda x: -norm(x), np.asarray(starts[k], dtype=float), method="L-BFGS-B", bounds=[tuple(b) for b in box])
        if -res.fun > best_v:
            best_x, best_v = np.asarray(res.x, dtype=float), float(-res.fun)
    if best_v <= L_h * (1 + 1e-9):
        return None
    return {"kind": "lipschitz", "x": best_x.tolist(), "norm": best_v, "L_h": L_h, "breaks": "Assumption 1: h Lipschitz"}


def attack(model: Model, arts: dict[str, Artefact], seed: int = 0) -> list[dict]:
    """Every counter-example found to a row the design only sampled (the LMI, L_h); [] when none is found or
    every such row is proved (a proved row needs no attack).

    Parameters
    ----------
    model : Model
        The spec's systems.
    arts : dict of str to Artefact
        Artefacts by stage; the checks ``stabilise.lmi_margin`` and ``bound.h_lipschitz`` decide which searches run.
    seed : int
        Seed of the searches' random starts.

    Returns
    -------
    list of dict
        The counter-examples of :func:`lmi_counterexample`, :func:`second_equilibrium` and :func:`lipschitz_counterexample`,
        in that order.
    """
    found = []
    lmi = arts["stabilise"].checks.get("lmi_margin")
    if lmi is not None and lmi.evidence != proofs.PROVED:
        for search in (lmi_counterexample, second_equilibrium):
            hit = search(model, arts, seed)
            if hit is not None:
                found.append(hit)
    lip = arts["bound"].checks.get("h_lipschitz")
    if lip is not None and lip.evidence != proofs.PROVED:
        hit = lipschitz_counterexample(model, arts, seed)
        if hit is not None:
            found.append(hit)
    return found
