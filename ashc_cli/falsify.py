"""Falsification: try hard to break the error bound of Theorem ErrorBound on a batch of random closed loops.

Each run draws a random initial abstract state xi0 in V and a concrete state x0 near p(xi0) (a quarter of
the runs start on the manifold, W(0) = 0; the rest off it, W(0) > 0), a random sequence of references xi_ref in
V with kappa(xi_ref) in Y, a random controller gain, and a random piecewise-constant disturbance on v, with
|v| clipped to the spec's v_max.  The whole batch is one vectorised ODE (numpy over the runs, one adaptive
LSODA integration per reference segment, see :data:`TOL`), never a Python loop over runs.

Along each run the guarantee is

    |psi(t) - y(t)| <= sqrt(W(0) exp(-(lambda - eps) t) / alpha_h) + G sup_{s <= t} |v(s)|

(Theorem ErrorBound with beta from the comparison lemma and the gain G of eq. egErrorBound); the command
reports the largest ratio measured / guaranteed over all runs and times, which must not exceed 1.  Times
after xi first leaves V are not counted (the theorem is local to V); how many runs left V is reported.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
import scipy.integrate as sint

from .artefacts import Artefact, Check
from .errors import DesignError, NumericalError
from .model import Model, compile_terms

NAME = "falsify"
SEGMENTS = 3
SAMPLES_PER_SEGMENT = 400
#: LSODA switches to a stiff method where it must: off the manifold a clipped input with the least-squares q
#: chatters where g(x) is small (the converter), which DOP853 cannot step through.
TOL = {"method": "LSODA", "rtol": 1e-8, "atol": 1e-10}
#: References and disturbances keep xi this fraction of V's width away from its edges.
REF_MARGIN = 0.05
#: Errors below this fraction of the output span count as zero (the integrator's accuracy).
FLOOR_RTOL = 1e-7


class BatchPlant:
    """The design's maps evaluated on a batch of points at once, fused into one compiled function of xi and
    one of x (each call returns every term, shape (N, rows, cols))."""

    def __init__(self, model: Model, arts: dict[str, Artefact]):
        xi_terms = {"phi": model.phi_bar, "delta": arts["delta"].expr("delta"), "l": model.l,
                    "dpd": arts["bound"].expr("dp_delta"), "p": arts["manifold"].expr("p"), "kappa": arts["kappa"].expr("kappa")}
        x_terms = {"f_bar": model.f_bar, "g": model.g, "h": model.h}
        self._xi = self._named(xi_terms, list(model.xi), model)
        self._x = self._named(x_terms, list(model.x), model)
        self.M = np.asarray(arts["stabilise"].value("M"), dtype=float)
        self.L = np.linalg.cholesky(self.M)
        self.K = np.asarray(arts["stabilise"].values.get("K", np.zeros((model.m, model.n))), dtype=float).reshape(model.m, model.n)

    @staticmethod
    def _named(terms: dict, args: list, model: Model):
        fun = compile_terms(list(terms.values()), args, model.values)
        return lambda points: dict(zip(terms, fun(points)))

    def at_xi(self, xi: np.ndarray) -> dict[str, np.ndarray]:
        """phi, delta, l, dpd (dp/dxi delta), p, kappa at the columns of xi (n_hat, N)."""
        return self._xi(xi)

    def at_x(self, x: np.ndarray) -> dict[str, np.ndarray]:
        """f_bar, g, h at the columns of x (n, N)."""
        return self._x(x)


def _pinv(a: np.ndarray) -> np.ndarray:
    """Pseudo-inverses of a stack (N, r, c); closed forms for one column or one row (zero where it is zero)."""
    if a.shape[2] == 1 or a.shape[1] == 1:
        norm2 = np.sum(a * a, axis=(1, 2), keepdims=True)
        safe = np.where(norm2 > 0, norm2, 1.0)
        return np.where(norm2 > 0, np.swapaxes(a, 1, 2) / safe, 0.0)
    return np.linalg.pinv(a)


def _controls(model: Model, plant: BatchPlant, xi: np.ndarray, x: np.ndarray, xi_ref: np.ndarray, gain: np.ndarray,
              noise: np.ndarray, v_max: float) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """v, u, xi' and x' for the batch (shapes (N, m_hat), (N, m), (N, n_hat), (N, n)): the set-point law plus
    noise, the interface u_w = sat(l + K (x - p) + q v) and the two systems."""
    a, b = plant.at_xi(xi), plant.at_x(x)
    v = np.einsum("Nij,Nj->Ni", _pinv(a["delta"]), gain[:, None] * (xi_ref - xi.T) - a["phi"][:, :, 0]) + noise
    v = np.clip(v, -v_max, v_max)
    u = a["l"][:, :, 0] + (x.T - a["p"][:, :, 0]) @ plant.K.T
    if model.spec.interface.q == "least_squares":
        A = np.einsum("ij,Njk->Nik", plant.L.T, a["dpd"])
        B = np.einsum("ij,Njk->Nik", plant.L.T, b["g"])
        u = u + np.einsum("Nij,Nj->Ni", _pinv(B) @ A, v)
    if model.spec.interface.saturate:
        u = np.clip(u, model.U[:, 0], model.U[:, 1])
    dxi = a["phi"][:, :, 0] + np.einsum("Nij,Nj->Ni", a["delta"], v)
    dx = b["f_bar"][:, :, 0] + np.einsum("Nij,Nj->Ni", b["g"], u)
    return v, u, dxi, dx


def _reference_pool(model: Model, plant: BatchPlant, rng: np.random.Generator, margin: float, count: int = 20000) -> np.ndarray:
    """Points of V, at least ``margin`` of its width inside, whose kappa lies in Y (rows)."""
    pad = margin * np.ptp(model.V, axis=1)[:, None]
    pts = rng.uniform(model.V[:, 0:1] + pad, model.V[:, 1:2] - pad, size=(model.n_hat, count))
    k = plant.at_xi(pts)["kappa"][:, :, 0].T
    keep = np.all((k >= model.Y[:, 0:1]) & (k <= model.Y[:, 1:2]), axis=0)
    if not keep.any():
        raise DesignError("concrete.output_set", "no sampled point of V has kappa in Y", "Y inside kappa(V)")
    return pts[:, keep].T


def falsify(model: Model, arts: dict[str, Artefact], runs: int, seed: int = 0, t_final: float | None = None,
            progress: Callable[[int], None] | None = None) -> Artefact:
    """Run the batch and measure the largest error / bound ratio.

    Parameters
    ----------
    model : Model
        The spec's systems (V already fixed).
    arts : dict
        Artefacts of stabilise, manifold, kappa, delta and bound.
    runs : int
        Batch size.
    seed : int
        Random seed (the batch is reproducible).
    t_final : float, optional
        Length of each run [default: the spec's tracking t_final, else 10 s].
    progress : callable, optional
        Called with the number of segments done after each one.

    Returns
    -------
    Artefact
        Values max_ratio, run_ratio (per run), where (run, time), the initial states, references, W0.
    """
    if runs < 1:
        raise DesignError("--runs", f"{runs}", "at least 1")
    plant = BatchPlant(model, arts)
    rng = np.random.default_rng(seed)
    tr = model.spec.simulate.tracking
    gain0 = tr.abstract_controller.gain if tr is not None else 1.0
    v_max = tr.abstract_controller.v_max if tr is not None else 1.0
    t_final = float(t_final if t_final is not None else (tr.t_final if tr is not None else 10.0))
    nh, n, mh = model.n_hat, model.n, model.m_hat
    bd = arts["bound"].values
    lam, eps, alpha_h, G = (float(bd[k]) for k in ("lambda", "epsilon", "alpha_h", "gain"))
    span = float(np.ptp(model.Y, axis=1).max())

    # Initial states: xi0 in V; x0 = p(xi0) + d with W(d) up to (10 % of the output span)^2 alpha_h.
    xi0 = rng.uniform(model.V[:, 0], model.V[:, 1], size=(runs, nh))
    p0 = plant.at_xi(xi0.T)["p"][:, :, 0]
    d = rng.standard_normal((runs, n))
    d /= np.sqrt(np.einsum("Ni,ij,Nj->N", d, plant.M, d))[:, None]
    W_target = rng.uniform(0, (0.1 * span) ** 2 * alpha_h, size=runs)
    W_target[: max(1, runs // 4)] = 0.0
    x0 = p0 + np.sqrt(W_target)[:, None] * d
    if model.state_box is not None:
        x0 = np.clip(x0, model.state_box[:, 0], model.state_box[:, 1])
    e0 = p0 - x0
    W0 = np.einsum("Ni,ij,Nj->N", e0, plant.M, e0)

    pool = _reference_pool(model, plant, rng, margin=REF_MARGIN)
    refs = pool[rng.integers(0, len(pool), size=(SEGMENTS, runs))]                # (S, N, n_hat)
    gains = gain0 * rng.uniform(0.5, 2.0, size=runs)
    # The disturbance moves the abstract equilibrium by at most delta noise / gain <= REF_MARGIN of V's width,
    # so xi stays in V (where the theorem applies) while v is still far from a clean set-point signal.
    delta_max = float(arts["delta"].value("max_singular_value"))
    amplitude = np.minimum(0.5 * v_max, REF_MARGIN * np.ptp(model.V, axis=1).min() * gains / max(delta_max, 1e-300))
    noise = rng.uniform(-1, 1, size=(SEGMENTS, runs, mh)) * amplitude[None, :, None]

    edges = np.linspace(0.0, t_final, SEGMENTS + 1)
    z = np.c_[xi0, x0].ravel()
    T, Z, V_in = [], [], []
    for s in range(SEGMENTS):
        def rhs(t, flat, s=s):
            zz = flat.reshape(runs, nh + n)
            xi, x = zz[:, :nh].T, zz[:, nh:].T
            _, _, dxi, dx = _controls(model, plant, xi, x, refs[s], gains, noise[s], v_max)
            return np.c_[dxi, dx].ravel()

        t_eval = np.linspace(edges[s], edges[s + 1], SAMPLES_PER_SEGMENT + 1)
        with np.errstate(all="ignore"):
            sol = sint.solve_ivp(rhs, (edges[s], edges[s + 1]), z, t_eval=t_eval, **TOL)
        if sol.status != 0 or not np.all(np.isfinite(sol.y)):
            raise NumericalError("falsify", f"the batch integration failed in segment {s + 1} ({sol.message})", "a finite closed loop")
        keep = slice(None) if s == 0 else slice(1, None)
        T.append(sol.t[keep])
        Zs = sol.y[:, keep].reshape(runs, nh + n, -1)
        Z.append(Zs)
        K = Zs.shape[2]
        flat = Zs.transpose(1, 0, 2).reshape(nh + n, runs * K)                      # column r K + k: run r, sample k
        vs, *_ = _controls(model, plant, flat[:nh], flat[nh:], np.repeat(refs[s], K, axis=0), np.repeat(gains, K),
                          np.repeat(noise[s], K, axis=0), v_max)
        V_in.append(np.linalg.norm(vs, axis=1).reshape(runs, K))
        z = sol.y[:, -1]
        if progress is not None:
            progress(s + 1)
    t = np.concatenate(T)
    Zall = np.concatenate(Z, axis=2)                                                # (N, nh + n, K)
    v_norm = np.concatenate(V_in, axis=1)
    xi_all, x_all = Zall[:, :nh, :], Zall[:, nh:, :]
    Kt = t.size
    psi = plant.at_xi(xi_all.transpose(1, 0, 2).reshape(nh, -1))["kappa"][:, :, 0]
    y = plant.at_x(x_all.transpose(1, 0, 2).reshape(n, -1))["h"][:, :, 0]
    err = np.linalg.norm(psi - y, axis=1).reshape(runs, Kt)                          # (N, K)
    bound = np.sqrt(W0[:, None] * np.exp(-(lam - eps) * t)[None, :] / alpha_h) + G * np.maximum.accumulate(v_norm, axis=1)
    in_V = np.all((xi_all >= model.V[None, :, 0:1] - 1e-9) & (xi_all <= model.V[None, :, 1:2] + 1e-9), axis=1)
    valid = np.logical_and.accumulate(in_V, axis=1)                                 # up to the first exit from V
    floor = FLOOR_RTOL * max(1.0, span)
    # Counted while xi is in V and the error is above the integrator's accuracy; a zero bound there is broken.
    ratio = np.where(valid & (err > floor), np.where(bound > 0, err / np.maximum(bound, 1e-300), np.inf), 0.0)
    run_ratio = ratio.max(axis=1)
    worst = int(np.argmax(run_ratio))
    worst_t = float(t[int(np.argmax(ratio[worst]))])
    max_ratio = float(run_ratio[worst])
    saturated = float(np.mean(v_norm >= v_max * (1 - 1e-12)))

    art = Artefact(stage=NAME, meta={"runs": runs, "seed": seed, "segments": SEGMENTS, "integrator": str(TOL),
                                      "bound": "sqrt(W0 exp(-(lambda - eps) t) / alpha_h) + G sup_{s<=t} |v(s)|",
                                      "vectorised": "one ODE over the whole batch (numpy), per reference segment"})
    art.values.update({
        "max_ratio": max_ratio, "run_ratio": run_ratio, "worst_run": worst, "worst_time": worst_t,
        "xi0": xi0, "x0": x0, "W0": W0, "references": refs, "gains": gains, "noise": noise, "t_final": t_final,
        "runs_leaving_V": int(np.sum(~valid[:, -1])), "max_error": float(err.max()),
        "largest_bound": float(bound.max()), "v_at_limit_fraction": saturated,
        "worst_t": t, "worst_error": err[worst], "worst_bound": bound[worst],
    })
    art.checks["falsify_ratio"] = Check(max_ratio, max_ratio <= 1.0, f"largest |psi - y| / guaranteed bound over {runs} random runs and all times (<= 1)")
    return art


def summarise(art: Artefact) -> dict:
    """Headline numbers for ``ashc summary``."""
    v = art.values
    return {"runs": int(art.meta["runs"]), "seed": int(art.meta["seed"]), "max_ratio": float(v["max_ratio"]),
            "worst_run": int(v["worst_run"]), "worst_time": float(v["worst_time"]), "runs_leaving_V": int(v["runs_leaving_V"]),
            "max_error": float(v["max_error"])}


def headline(art: Artefact) -> str:
    """One line."""
    v = art.values
    return (f"{art.meta['runs']} runs: largest error / bound = {v['max_ratio']:.4g} (run {v['worst_run']}, t = {v['worst_time']:.4g} s); "
            f"{v['runs_leaving_V']} left V")
