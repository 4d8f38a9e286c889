"""Grids over the abstract domain V and samples of the concrete state region X_y = {x : h(x) in Y}.

Every stage that checks a result numerically uses these, so checks are made on the same points.
"""

from __future__ import annotations

import numpy as np

__all__ = ["domain_grid", "maximise_on_box", "sample_output_region", "sample_states_with_output"]


def domain_grid(V: np.ndarray, points: int) -> np.ndarray:
    """A tensor grid over the box V with about ``points`` points in all.

    Parameters
    ----------
    V : ndarray, shape (n_hat, 2)
        The box [lo, hi] per abstract state.
    points : int
        Total number of points wanted (per axis: points ** (1 / n_hat), at least 3).

    Returns
    -------
    ndarray, shape (n_hat, N)
        One column per grid point, endpoints included.
    """
    V = np.asarray(V, dtype=float)
    per_axis = max(3, int(round(points ** (1.0 / len(V)))))
    axes = [np.linspace(lo, hi, per_axis) for lo, hi in V]
    mesh = np.meshgrid(*axes, indexing="ij")
    return np.stack([m.ravel() for m in mesh], axis=0)


def maximise_on_box(pts: np.ndarray, vals: np.ndarray, value_at, box: np.ndarray, starts: int = 1) -> tuple[float, np.ndarray]:
    """The largest value of a function on a box: its values on a grid, refined by bounded L-BFGS-B.

    Parameters
    ----------
    pts, vals : ndarray, shapes (d, N) and (N,)
        Grid points of the box (:func:`domain_grid`) and the function's values there.
    value_at : callable
        value_at(point (d,)) -> float, the function at one point (for the local searches).
    box : ndarray, shape (d, 2)
    starts : int
        How many of the best grid points start a local search.

    Returns
    -------
    best : float
    at : ndarray, shape (d,)
    """
    import scipy.optimize as sopt

    k = int(np.argmax(vals))
    best, at = float(vals[k]), pts[:, k]
    for k in np.argsort(vals)[-starts:]:
        res = sopt.minimize(lambda x: -value_at(x), pts[:, k], bounds=[tuple(b) for b in box], method="L-BFGS-B")
        if res.success and -res.fun > best:
            best, at = float(-res.fun), res.x
    return best, np.asarray(at, dtype=float)


def sample_output_region(C: np.ndarray, Y: np.ndarray, box: np.ndarray, count: int, seed: int = 0) -> np.ndarray:
    """Random points x with C x in Y, the other directions uniform in ``box`` (linear h only).

    Parameters
    ----------
    C : ndarray, shape (p, n)
        The output matrix of h(x) = C x.
    Y : ndarray, shape (p, 2)
        The output box.
    box : ndarray, shape (n, 2)
        Where the unconstrained directions are drawn from.
    count : int
        How many points.
    seed : int
        Random seed (results are reproducible).

    Returns
    -------
    ndarray, shape (n, count)
    """
    rng = np.random.default_rng(seed)
    n = C.shape[1]
    x = rng.uniform(box[:, 0:1], box[:, 1:2], size=(n, count))
    y = rng.uniform(Y[:, 0:1], Y[:, 1:2], size=(len(Y), count))
    # Move x along C's row space so that C x = y exactly: x <- x + C^+ (y - C x).
    return x + np.linalg.pinv(C) @ (y - C @ x)


def sample_states_with_output(h, C: np.ndarray | None, Y: np.ndarray, box: np.ndarray, count: int, seed: int = 0) -> np.ndarray:
    """Random points x of X_y = {x : h(x) in Y}: exact for linear h, by rejection from ``box`` otherwise.

    Parameters
    ----------
    h : callable
        h(*x) for arrays, returning shape (p, 1, N) (a lambdified output map).
    C : ndarray or None
        The output matrix if h is linear (then :func:`sample_output_region` is used).
    Y, box, count, seed
        As :func:`sample_output_region`.

    Returns
    -------
    ndarray, shape (n, k)
        k <= count points (k = count for linear h; fewer if the box rarely meets X_y).
    """
    if C is not None:
        return sample_output_region(C, Y, box, count, seed)
    rng = np.random.default_rng(seed)
    kept = []
    total = 0
    for _ in range(20):
        x = rng.uniform(box[:, 0:1], box[:, 1:2], size=(len(box), 20 * count))
        y = np.asarray(h(*x))[:, 0, :]
        keep = np.all((y >= Y[:, 0:1]) & (y <= Y[:, 1:2]), axis=0)
        kept.append(x[:, keep])
        total += int(keep.sum())
        if total >= count:
            break
    return np.concatenate(kept, axis=1)[:, :count]
