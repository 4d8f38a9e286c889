"""The runs the falsifier draws: its batch, the numpy form of its loop, and the strategies.

The runs are not only drawn at random: the falsifier *searches*.  Every run keeps ||v(t)|| <= v_limit = min(the
spec's tracking ``v_max`` (or 1), ``v_max_certified``) and starts with W(0) <= ``w0_max_certified``.  Most
strategies hold v constant over a common grid of ``holds`` (piecewise-constant v, so the bound's sup ||v|| is
exact) and choose its amplitude too: in the linear regime the ratio does not depend on it, and a small one
keeps xi near the point of V it starts from.  A held input that would carry xi out of V within two holds is
reversed (or pointed at V's centre).  The strategies, each a share of the runs (:data:`SHARES`), are

``random``
    today's draws: xi0 in V, x0 near p(xi0) (a quarter on the manifold), random references with kappa in Y,
    random set-point gains and random piecewise-constant disturbances on v (the set-point law, continuous in
    the state, its norm clipped to v_limit).
``controller`` (only with ``abstract_controller.kind: registered``)
    every other random run, closed with the spec's registered law as it is: no noise, no guard, its norm
    clipped to v_limit (mode CONTROLLER; :mod:`~ashc_cli.closedloop.controllers`).
``greedy`` and ``square`` (on the manifold, x0 = p(xi0), xi0 across V including near both edges)
    ``greedy``: a state-feedback adversary; at the start of every hold it picks, among the inputs of its
    amplitude (+-v for one abstract input), the one that maximises a one-hold look-ahead of
    rho W / alpha_h + (1 - rho) ||dh/dx e||^2, e = p(xi) - x (rho = 1: the v that maximises the growth of W,
    the saturation included), kept for at least ``dwell`` holds (hysteresis against chattering).
    ``square``: bang-bang square waves v = a dir sign(sin(2 pi (f t + phase))), f from 1 / t_final to a
    quarter of the hold rate, half at full amplitude, half with the amplitude fitted to V.
``linearised``
    at points of V the loop linearised about (xi, p(xi)) with v held over each hold is e+ = E e + Gamma v,
    e_y = C e.  The input of norm a that maximises |e_y| after K holds is v_i = a normalise(C E^(K-1-i) Gamma)^T w
    (bang-bang for one input); it is repeated with alternating sign.  Its gain sum_k ||C E^k Gamma|| / G is the
    linearised worst ratio at that point (``linearised_worst_ratio``: 0.157 on the Cuk converter, at xi = 0).
    The runs start where that ratio is largest and across V, with a fitted so that xi stays within 1 %, 3 % or
    10 % of V's width; every third top point gets a square wave at the frequency of the largest linearised gain.
``off_manifold``
    x0 on the boundary of the certified region, W(0) = ``w0_max_certified``, or, when the bound is global,
    W(0) spread over 10^-2 .. 10^6 times (output span)^2 alpha_h.  The directions are those of the largest
    output error (M^-1 dh/dx^T: the bound is tight there at t = 0), the least stable modes of the linearised
    loop, the principal axes of M and a random one.  Half have v = 0, half the W-greedy adversary.
``refined``
    the best runs (always including the best one on the manifold; runs off it ranked after t = 0, where
    their ratio is 1 by construction) are refined by a derivative-free (1 + lambda) evolution strategy over
    their parameters: xi0, frequency, phase and amplitude, look-ahead weight and dwell, pattern length and
    phase, direction and size of x0 - p(xi0).  Each generation is one batch for all seeds together, the
    step halving per generation (a fixed budget of :data:`REFINE_SHARE` of the runs).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field, fields

import numpy as np

from ashc_cli.errors import DesignError
from ashc_cli.problem.model import Model
from ashc_cli.closedloop.batch import BatchPlant
from ashc_cli.products.falsify_linear import discrete

#: Reference segments of the random strategy.
REF_SEGMENTS = 3
#: Search integration: embedded Dormand-Prince 5(4), error per run relative to the state's scale.
TOL = {"method": "Dormand-Prince 5(4)", "rtol": 1e-5, "atol": 1e-9}
#: Verification of the runs that decide the reported numbers.
TOL_VERIFY = {"method": "Dormand-Prince 5(4)", "rtol": 1e-7, "atol": 1e-11}
#: The verified runs once more, 100 times tighter: where the two disagree is the verification's own integration
#: error, which a violation must exceed (an integrator keeps an error of about rtol |x| however long the run).
TOL_FINE = {"method": "Dormand-Prince 5(4)", "rtol": 1e-9, "atol": 1e-13}
#: References and disturbances keep xi this fraction of V's width away from its edges.
REF_MARGIN = 0.05
#: Errors below this fraction of the output span count as zero (the integrator's accuracy).
FLOOR_RTOL = 1e-7
#: Most hold intervals per run; the hold is at most t_final / MIN_HOLDS.
MAX_HOLDS = 4000
MIN_HOLDS = 100
#: A held input is turned around when xi would leave V within this many holds.
GUARD_LOOKAHEAD = 2.0
#: Shares of the first batch (the refinement gets REFINE_SHARE of all runs).
SHARES = {"random": 0.15, "manifold": 0.35, "linearised": 0.2, "off_manifold": 0.3}
REFINE_SHARE = 0.2
#: Below this many runs nothing is kept back for refinement.
REFINE_MIN_RUNS = 12
REFINE_SEEDS = 3
REFINE_GENERATIONS = 2
#: Runs verified per headline number and round, most rounds; and runs above 1 verified per round (largest first).
VERIFY_TOP = 1
VERIFY_ROUNDS = 8
VERIFY_ABOVE_ONE = 64
#: Open-loop inputs (square waves, linearised patterns) start with an amplitude that moves xi over at most this
#: fraction of V's width, and from an xi0 shifted so that xi stays in V.
EXCURSION = 0.1
#: Amplitudes of v searched, as log10 of the fraction of v_limit.
AMP_DECADES = (-3.0, 0.0)
#: Off the manifold with a global bound: W(0) / ((output span)^2 alpha_h) spread over these decades.
W0_DECADES = (-2.0, 6.0)
#: A run whose state exceeds this multiple of its scale has diverged (counted up to there, then frozen).
DIVERGED = 1e12
STRATEGIES = ("random", "greedy", "square", "linearised", "off_manifold", "refined")
#: The runs that close the loop with the spec's registered controller (half the random runs, when it has one).
CONTROLLER_STRATEGY = "controller"
#: Length of each run when neither --t-final nor the spec's tracking scenario gives one.
DEFAULT_T_FINAL = 10.0

SETPOINT, TABLE, GREEDY, CONTROLLER = 0, 1, 2, 3


def _reference_pool(model: Model, plant: BatchPlant, rng: np.random.Generator, margin: float, count: int = 20000) -> np.ndarray:
    """Points of V, at least ``margin`` of its width inside, whose kappa lies in Y (rows)."""
    pad = margin * np.ptp(model.V, axis=1)[:, None]
    pts = rng.uniform(model.V[:, 0:1] + pad, model.V[:, 1:2] - pad, size=(model.n_hat, count))
    k = plant.at_xi(pts)["kappa"][:, :, 0].T
    keep = np.all((k >= model.Y[:, 0:1]) & (k <= model.Y[:, 1:2]), axis=0)
    if not keep.any():
        raise DesignError("concrete.output_set", "no sampled point of V has kappa in Y", "Y inside kappa(V)")
    return pts[:, keep].T


# --- the setting of a search ----------------------------------------------------------------------------


@dataclass
class Setup:
    """What every batch of a search shares: the design, the bound, the hold grid, the limits."""

    model: Model
    plant: BatchPlant
    t_final: float
    holds: int
    hold: float
    v_limit: float
    w0_max: float
    v_max_certified: float
    lam: float
    eps: float
    alpha_h: float
    G: float
    span: float
    floor: float
    scale: np.ndarray            # per state of (xi, x): the absolute tolerance's unit
    gain0: float
    v_max_spec: float
    delta_max: float = 1.0
    lin: dict | None = None
    loop: object | None = None          # the compiled runs (falsify_loop.FalsifyLoop)
    on_runs: Callable[[int, int, float], None] | None = None   # (runs done, of, seconds) after each compiled chunk
    controller: tuple | None = None     # the spec's registered controller: (compiled law, its parameters)

    @property
    def t(self) -> np.ndarray:
        return np.linspace(0.0, self.t_final, self.holds + 1)


@dataclass
class Batch:
    """Runs integrated together (arrays over runs).  ``mode``: SETPOINT (the random strategy's set-point law,
    continuous in the state), TABLE (v held per interval from ``vtab``) or GREEDY (the state-feedback
    adversary, held per interval); held inputs are turned around near V's edges where ``guard``."""

    strategy: list
    xi0: np.ndarray      # (N, n_hat)
    x0: np.ndarray       # (N, n)
    mode: np.ndarray     # (N,)
    vtab: np.ndarray     # (N, holds, m_hat)
    rho: np.ndarray      # (N,)
    dwell: np.ndarray    # (N,)
    amp: np.ndarray      # (N,) fraction of v_limit of the greedy adversary and of the guard's input
    guard: np.ndarray    # (N,)
    refs: np.ndarray     # (S, N, n_hat)
    gains: np.ndarray    # (N,)
    noise: np.ndarray    # (S, N, m_hat)
    params: list = field(default_factory=list)   # per run: (kind, off, vector) for refinement, or None
    origin: np.ndarray | None = None            # per run: the run it was refined from (-1: none)

    def __len__(self) -> int:
        return len(self.mode)

    @staticmethod
    def concat(parts: list[Batch]) -> Batch:
        parts = [p for p in parts if len(p)]
        out = {}
        for f in fields(Batch):
            vals = [getattr(p, f.name) for p in parts]
            if f.name in ("strategy", "params"):
                out[f.name] = [x for v in vals for x in v]
            elif f.name in ("refs", "noise"):
                out[f.name] = np.concatenate(vals, axis=1)
            elif f.name == "origin":
                out[f.name] = np.concatenate([v if v is not None else np.full(len(p), -1) for v, p in zip(vals, parts)])
            else:
                out[f.name] = np.concatenate(vals, axis=0)
        return Batch(**out)

    def take(self, idx) -> Batch:
        idx = np.asarray(idx, dtype=int)
        out = {}
        for f in fields(Batch):
            v = getattr(self, f.name)
            if f.name in ("strategy", "params"):
                out[f.name] = [v[i] for i in idx]
            elif f.name in ("refs", "noise"):
                out[f.name] = v[:, idx]
            elif f.name == "origin":
                out[f.name] = None if v is None else v[idx]
            else:
                out[f.name] = v[idx]
        return Batch(**out)


def _empty(st: Setup, count: int, strategy: str, mode: int) -> Batch:
    m = st.model
    return Batch(strategy=[strategy] * count, xi0=np.zeros((count, m.n_hat)), x0=np.zeros((count, m.n)),
                 mode=np.full(count, mode), vtab=np.zeros((count, st.holds, m.m_hat)), rho=np.ones(count),
                 dwell=np.ones(count, dtype=int), amp=np.ones(count), guard=np.full(count, mode != SETPOINT),
                 refs=np.zeros((REF_SEGMENTS, count, m.n_hat)), gains=np.zeros(count),
                 noise=np.zeros((REF_SEGMENTS, count, m.m_hat)), params=[None] * count)


# --- integration -------------------------------------------------------------------------------------------

def unit_candidates(m_hat: int) -> np.ndarray:
    """Inputs of unit norm the greedy adversary chooses from: +-e_j and +-(e_i +- e_j) / sqrt 2.

    Parameters
    ----------
    m_hat : int
        Abstract inputs.
    """
    eye = np.eye(m_hat)
    rows = [eye, -eye]
    if 1 < m_hat <= 4:
        for i in range(m_hat):
            for j in range(i + 1, m_hat):
                for si in (1, -1):
                    for sj in (1, -1):
                        rows.append(((si * eye[i] + sj * eye[j]) / np.sqrt(2.0))[None])
    return np.concatenate(rows, axis=0)


def w0(st: Setup, b: Batch) -> np.ndarray:
    """W(xi0, x0) = (p(xi0) - x0)^T M (p(xi0) - x0) per run (exactly 0 on the manifold).

    Parameters
    ----------
    st : Setup
    b : Batch
    """
    e0 = st.plant.at_xi(b.xi0.T)["p"][:, :, 0] - b.x0
    W0 = np.maximum(np.einsum("Ni,ij,Nj->N", e0, st.plant.M, e0), 0.0)
    W0[np.all(e0 == 0, axis=1)] = 0.0
    return W0


def integrate(st: Setup, b: Batch, tol: dict, record: bool = False, progress: Callable[[float], None] | None = None) -> dict:
    """The runs of ``b``: compiled, each run with its own step size, over every core (:meth:`ashc_cli.closedloop.falsify_loop.FalsifyLoop.run`,
    whose result this is, without ``vused``: see :func:`replay`).

    Parameters
    ----------
    st : Setup
    b : Batch
    tol : dict
        :data:`TOL` or :data:`TOL_VERIFY`.
    record : bool
        Keep the series at the hold boundaries.
    progress : callable, optional
        Called with the fraction of runs done.
    """
    def report(done: int, total: int, seconds: float) -> None:
        if st.on_runs is not None:
            st.on_runs(done, total, seconds)
        if progress is not None:
            progress(done / max(total, 1))
    return st.loop.run(st, b, tol, unit_candidates(st.model.m_hat), w0(st, b), DIVERGED, GUARD_LOOKAHEAD, record, report,
                       keep_inputs=False)


def _pattern(st: Setup, disc: dict, g: int, length: int, offset: float, wsel: int | None = None) -> np.ndarray:
    """The linearised worst input at grid point g at full amplitude: v_i = v_limit normalise(m_{K-1-i}^T w),
    i < K, repeated with alternating sign, started ``offset`` of a period late (holds, m_hat)."""
    mk = disc["marks"][g]                                                            # (K, p, mh)
    K = int(np.clip(length, 1, mk.shape[0]))
    w = disc["W"][disc["wbest"][g] if wsel is None else wsel % len(disc["W"])]
    rows = np.einsum("p,Kpm->Km", w, mk[:K])[::-1]                                  # v_0 .. v_{K-1}
    nr = np.linalg.norm(rows, axis=1, keepdims=True)
    # Where the linearised response vanishes (theta = 0 there) the pattern is a square wave of period 2 K.
    unit = np.zeros(rows.shape[1])
    unit[0] = 1.0
    rows = np.where(nr > 1e-12 * max(float(nr.max()), 1e-300), rows / np.where(nr > 0, nr, 1.0), unit) * st.v_limit
    i = np.arange(st.holds) + int(round(offset * K))
    sign = np.where((i // K) % 2 == 0, 1.0, -1.0)
    return rows[i % K] * sign[:, None]


def _square(st: Setup, f: float, phase: float, direction: np.ndarray) -> np.ndarray:
    """v = v_limit dir sign(sin(2 pi (f t + phase))) sampled at the middle of each hold (holds, m_hat)."""
    tm = (np.arange(st.holds) + 0.5) * st.hold
    s = np.sign(np.sin(2 * np.pi * (f * tm + phase)))
    s[s == 0] = 1.0
    d = np.asarray(direction, dtype=float)
    d = d / max(float(np.linalg.norm(d)), 1e-300)
    return s[:, None] * d[None, :] * st.v_limit


def _excursion(st: Setup, xi0: np.ndarray, vtab: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Lowest and highest displacement of xi from xi0 under a held input at full amplitude, delta frozen at xi0
    (the drift phi_bar left out): the extremes of hold * cumsum(delta(xi0) v_i)."""
    delta0 = st.plant.at_xi(xi0[:, None])["delta"][0]                                 # (nh, mh)
    path = np.cumsum(vtab @ delta0.T, axis=0) * st.hold
    path = np.vstack([np.zeros((1, len(xi0))), path])
    return path.min(axis=0), path.max(axis=0)


def _fit_amplitude(st: Setup, xi0: np.ndarray, vtab: np.ndarray, excursion: float = EXCURSION) -> float:
    """The fraction of v_limit that keeps xi's excursion under a held input within ``excursion`` of V's width."""
    lo, hi = _excursion(st, xi0, vtab)
    spread = hi - lo
    width = np.ptp(st.model.V, axis=1)
    with np.errstate(divide="ignore", invalid="ignore"):
        frac = np.where(spread > 0, excursion * width / spread, np.inf)
    return float(np.clip(np.min(frac), 10 ** AMP_DECADES[0], 1.0))


def _shift_into_V(st: Setup, xi0: np.ndarray, vtab: np.ndarray) -> np.ndarray:
    """xi0 moved (as little as possible) so that xi stays in V under the held input (delta frozen); where the
    excursion does not fit in V, xi0 stays (in V) and the guard turns the input around at V's edges."""
    lo, hi = _excursion(st, xi0, vtab)
    V = st.model.V
    pad = 0.005 * np.ptp(V, axis=1)
    a, b = V[:, 0] - lo + pad, V[:, 1] - hi - pad
    return np.clip(np.where(a <= b, np.clip(xi0, a, b), xi0), V[:, 0], V[:, 1])


# --- run parameters (for the strategies and the refinement) --------------------------------------------------


def _param_bounds(st: Setup, kind: str, off: bool, w0_free: bool, disc: dict) -> tuple[np.ndarray, np.ndarray]:
    """Box of a kind's parameter vector: xi0 | law (with log10 amplitude / v_limit) | x0 - p(xi0) direction, log10 W0.

    square: log10 f, phase, log10 amplitude, direction (several abstract inputs); greedy: rho, log2 dwell,
    log10 amplitude; pattern: log10 K, offset, output direction, log10 amplitude; free (v = 0): nothing.
    """
    m = st.model
    lo, hi = list(m.V[:, 0]), list(m.V[:, 1])
    f_lo, f_hi = 1.0 / st.t_final, 0.25 / st.hold
    many = m.m_hat if m.m_hat > 1 else 0
    if kind == "square":
        lo += [np.log10(f_lo), 0.0, AMP_DECADES[0]] + [-1.0] * many
        hi += [np.log10(f_hi), 1.0, AMP_DECADES[1]] + [1.0] * many
    elif kind == "greedy":
        lo += [0.0, 0.0, AMP_DECADES[0]]
        hi += [1.0, 3.0, AMP_DECADES[1]]
    elif kind == "pattern":
        lo += [np.log10(2.0), 0.0, 0.0, AMP_DECADES[0]]
        hi += [np.log10(max(2.0, disc["marks"].shape[1])), 1.0, 1.0, AMP_DECADES[1]]
    if off:
        lo += [-1.0] * m.n + ([W0_DECADES[0]] if w0_free else [])
        hi += [1.0] * m.n + ([W0_DECADES[1]] if w0_free else [])
    return np.array(lo, dtype=float), np.array(hi, dtype=float)


def _law_table(st: Setup, kind: str, xi0: np.ndarray, law: np.ndarray, disc: dict, lin: dict) -> np.ndarray:
    """The full-amplitude held input of an open-loop kind (holds, m_hat)."""
    mh = st.model.m_hat
    if kind == "square":
        direction = law[3:3 + mh] if mh > 1 else np.ones(1)
        if not np.any(direction):
            direction = np.ones(mh)
        return _square(st, 10 ** law[0], law[1], direction)
    g = int(np.argmin(np.sum((lin["xi"].T - xi0) ** 2, axis=1)))
    W = len(disc["W"])
    return _pattern(st, disc, g, int(round(10 ** law[0])), law[1], int(law[2] * W) if W > 1 else None)


def _decode(st: Setup, kind: str, off: bool, w0_free: bool, vec: np.ndarray, disc: dict, lin: dict) -> Batch:
    """One run from a parameter vector (see :func:`_param_bounds`)."""
    m = st.model
    nh, n, mh = m.n_hat, m.n, m.m_hat
    xi0 = np.clip(vec[:nh], m.V[:, 0], m.V[:, 1])
    b = _empty(st, 1, kind, GREEDY if kind == "greedy" else TABLE)
    i = nh
    if kind in ("square", "pattern"):
        size = 3 + (mh if mh > 1 else 0) if kind == "square" else 4
        law = vec[i:i + size]
        amp = 10 ** float(law[2] if kind == "square" else law[3])
        table = _law_table(st, kind, xi0, law, disc, lin) * amp
        xi0 = _shift_into_V(st, xi0, table)
        b.vtab[0] = table
        i += size
    elif kind == "greedy":
        b.rho[0] = float(np.clip(vec[i], 0, 1))
        b.dwell[0] = int(round(2 ** np.clip(vec[i + 1], 0, 3)))
        b.amp[0] = 10 ** float(np.clip(vec[i + 2], *AMP_DECADES))
        i += 3
    else:   # "free": v = 0 throughout (no guard: the run tests W0 alone)
        b.guard[0] = False
    p0 = st.plant.at_xi(xi0[:, None])["p"][0, :, 0]
    x0 = p0.copy()
    if off:
        d = vec[i:i + n]
        if not np.any(d):
            d = np.ones(n)
        d = d / np.sqrt(d @ st.plant.M @ d)
        W0 = st.w0_max * (1 - 1e-6) if not w0_free else st.span ** 2 * st.alpha_h * 10 ** vec[i + n]
        x0 = p0 + np.sqrt(W0) * d
        if st.model.state_box is not None:
            x0 = np.clip(x0, st.model.state_box[:, 0], st.model.state_box[:, 1])
    b.xi0[0], b.x0[0] = xi0, x0
    b.params = [(kind, off, np.array(vec, dtype=float))]
    return b


def _runs(st: Setup, specs: list[tuple[str, bool, np.ndarray]], disc: dict, lin: dict, strategy: str | None = None) -> Batch:
    w0_free = not np.isfinite(st.w0_max)
    parts = [_decode(st, kind, off, w0_free, vec, disc, lin) for kind, off, vec in specs]
    out = Batch.concat(parts) if parts else _empty(st, 0, "none", TABLE)
    if strategy is not None:
        out.strategy = [strategy] * len(out)
    return out


def _open_loop(st: Setup, kind: str, xi0: np.ndarray, law: list, disc: dict, lin: dict, full: bool,
               excursion: float = EXCURSION) -> np.ndarray:
    """The parameter vector of an open-loop run with its amplitude fitted to V (or full amplitude)."""
    law = np.array(law, dtype=float)
    at = 2 if kind == "square" else 3
    if full:
        law[at] = 0.0
    else:
        law[at] = np.log10(_fit_amplitude(st, xi0, _law_table(st, kind, xi0, law, disc, lin), excursion))
    return np.r_[xi0, law]


# --- the strategies -------------------------------------------------------------------------------------------


def _allocate(runs: int) -> dict[str, int]:
    """Runs per strategy: REFINE_SHARE for the refinement (from REFINE_MIN_RUNS runs on), the rest by SHARES."""
    refine = int(round(REFINE_SHARE * runs)) if runs >= REFINE_MIN_RUNS else 0
    main = runs - refine
    order = ["linearised", "off_manifold", "manifold", "random"]
    counts = dict.fromkeys(order, 0)
    if main < len(order):
        for name in order[:main]:
            counts[name] = 1
    else:
        for name in order:
            counts[name] = 1
        rest = main - len(order)
        raw = {k: SHARES[k] * rest for k in order}
        for k in order:
            counts[k] += int(np.floor(raw[k]))
        left = main - sum(counts.values())
        for k in sorted(order, key=lambda k: raw[k] - np.floor(raw[k]), reverse=True)[:left]:
            counts[k] += 1
    counts["refined"] = refine
    return counts


def _spread(lo: np.ndarray, hi: np.ndarray, count: int, rng: np.random.Generator, edge: float = 0.02) -> np.ndarray:
    """count points of the box: near both edges first (``edge`` of the width inside), then a Latin hypercube (rows)."""
    nh = len(lo)
    width = hi - lo
    pts = []
    for j in range(min(count, 2 * nh)):
        pt = rng.uniform(lo + edge * width, hi - edge * width)
        axis, side = j // 2, j % 2
        pt[axis] = lo[axis] + (edge if side == 0 else 1 - edge) * width[axis]
        pts.append(pt)
    rest = count - len(pts)
    if rest > 0:
        u = (np.stack([rng.permutation(rest) for _ in range(nh)], axis=1) + rng.uniform(0, 1, (rest, nh))) / rest
        pts.extend(lo + u * width)
    return np.array(pts, dtype=float).reshape(count, nh)


def _random_runs(st: Setup, count: int, rng: np.random.Generator) -> Batch:
    """Today's random draws: xi0 in V, x0 near p(xi0) (a quarter on the manifold), set-point references in V with
    kappa in Y, random gains and bounded disturbances (the set-point law clipped to v_limit)."""
    model, plant = st.model, st.plant
    nh, n, mh = model.n_hat, model.n, model.m_hat
    b = _empty(st, count, "random", SETPOINT)
    if count == 0:
        return b
    xi0 = rng.uniform(model.V[:, 0], model.V[:, 1], size=(count, nh))
    p0 = plant.at_xi(xi0.T)["p"][:, :, 0]
    d = rng.standard_normal((count, n))
    d /= np.sqrt(np.einsum("Ni,ij,Nj->N", d, plant.M, d))[:, None]
    W_target = rng.uniform(0, min((0.1 * st.span) ** 2 * st.alpha_h, st.w0_max * (1 - 1e-6)), size=count)
    W_target[: max(1, count // 4)] = 0.0
    x0 = p0 + np.sqrt(W_target)[:, None] * d
    if model.state_box is not None:
        x0 = np.clip(x0, model.state_box[:, 0], model.state_box[:, 1])
    pool = _reference_pool(model, plant, rng, margin=REF_MARGIN)
    b.xi0, b.x0 = xi0, x0
    b.refs = pool[rng.integers(0, len(pool), size=(REF_SEGMENTS, count))]
    b.gains = st.gain0 * rng.uniform(0.5, 2.0, size=count)
    # The disturbance moves the abstract equilibrium by at most delta noise / gain <= REF_MARGIN of V's width.
    amplitude = np.minimum(0.5 * st.v_limit, REF_MARGIN * np.ptp(model.V, axis=1).min() * b.gains / max(st.delta_max, 1e-300))
    b.noise = rng.uniform(-1, 1, size=(REF_SEGMENTS, count, mh)) * amplitude[None, :, None]
    return b


def _directions(st: Setup, lin: dict, g: int, rng: np.random.Generator) -> list[np.ndarray]:
    """Directions of x0 - p(xi0): the largest output error (M^-1 dh/dx^T), the least stable modes of the
    linearised loop, the principal axes of M, each with both signs, and one random direction."""
    M = st.plant.M
    out = []
    for row in lin["C"][g]:
        if np.any(row):
            out.append(np.linalg.solve(M, row))
    w, vecs = np.linalg.eig(lin["J"][g])
    for k in np.argsort(-w.real)[:2]:
        out.extend([vecs[:, k].real, vecs[:, k].imag])
    _, U = np.linalg.eigh(M)
    out.extend(U.T)
    out = [d for d in out if np.linalg.norm(d) > 1e-12]
    full = []
    for d in out:
        full.extend([d, -d])
    full.append(rng.standard_normal(st.model.n))
    return full


def _first_batch(st: Setup, counts: dict, rng: np.random.Generator, lin: dict, disc: dict) -> Batch:
    """The runs of every strategy but the refinement, in one batch."""
    model = st.model
    mh = model.m_hat
    lo, hi = model.V[:, 0], model.V[:, 1]
    w0_free = not np.isfinite(st.w0_max)
    f_lo, f_hi = 1.0 / st.t_final, 0.25 / st.hold
    rand = _random_runs(st, counts["random"], rng)
    if st.controller is not None:       # every other random run closes the loop with the spec's controller as it is
        own = np.arange(len(rand)) % 2 == 1
        rand.mode[own], rand.noise[:, own], counts[CONTROLLER_STRATEGY] = CONTROLLER, 0.0, int(own.sum())
        rand.strategy = [CONTROLLER_STRATEGY if o else s for o, s in zip(own, rand.strategy)]
        counts["random"] -= counts[CONTROLLER_STRATEGY]

    def direction():
        return list(rng.standard_normal(mh)) if mh > 1 else []

    # On the manifold: greedy adversaries (full amplitude and smaller) and square waves (half at full amplitude,
    # turned around by the guard near V's edges; half with the amplitude fitted to V), xi0 across V.
    nm = counts["manifold"]
    ng = (nm + 1) // 2
    xs = _spread(lo, hi, ng, rng)
    settings = [(1.0, 0.0, 0.0), (0.0, 0.0, 0.0), (1.0, 1.0, -1.0), (0.5, 2.0, 0.0), (1.0, 0.0, -2.0), (0.0, 1.0, -1.0)]
    greedy = [("greedy", False, np.r_[xs[j], settings[j % len(settings)]]) for j in range(ng)]
    ns = nm - ng
    xs = _spread(lo, hi, ns, rng)
    freqs = np.geomspace(f_lo, f_hi, max(ns, 1))[rng.permutation(max(ns, 1))]
    square = [("square", False, _open_loop(st, "square", xs[j], [np.log10(freqs[j]), rng.uniform(), 0.0] + direction(),
                                           disc, lin, full=j % 2 == 0)) for j in range(ns)]
    man = _runs(st, greedy, disc, lin, "greedy")
    sq = _runs(st, square, disc, lin, "square")

    # Linearised worst case: the pattern at the points of V where its ratio is largest, then across V, the
    # amplitude fitted so that xi stays within 1 %, 3 % or 10 % of V's width of the point (the linearised ratio
    # does not depend on the amplitude, but it can fall fast away from the point); every third top point a
    # square wave at its worst frequency.
    nl = counts["linearised"]
    width = np.ptp(model.V, axis=1)
    picked = []
    for g in np.argsort(-disc["ratio"]):
        if all(np.max(np.abs(lin["xi"][:, g] - lin["xi"][:, q]) / width) > 0.03 for q in picked):
            picked.append(int(g))
        if len(picked) >= max(1, (nl + 1) // 2):
            break
    across = np.linspace(0, lin["xi"].shape[1] - 1, max(1, nl - len(picked))).round().astype(int)
    K = disc["marks"].shape[1]
    specs = []
    for j in range(nl):
        g = picked[j] if j < len(picked) else int(across[j - len(picked)])
        xi_g = lin["xi"][:, g]
        if j < len(picked) and j % 3 == 2:
            f = float(np.clip(disc["f_star"][g], f_lo, f_hi))
            specs.append(("square", False, _open_loop(st, "square", xi_g, [np.log10(f), 0.0, 0.0] + direction(), disc, lin, False, 0.01)))
        else:
            wsel = (disc["wbest"][g] + 0.5) / len(disc["W"])
            specs.append(("pattern", False, _open_loop(st, "pattern", xi_g, [np.log10(max(2, K)), 0.0, wsel, 0.0], disc, lin, False,
                                                       (0.01, 0.03, 0.1)[j % 3])))
    lin_runs = _runs(st, specs, disc, lin, "linearised")

    # Off the manifold: x0 on the boundary of the certified W0 region (or W0 over decades when it is global), in
    # the directions of _directions; half with v = 0, half with the W-greedy adversary.
    no = counts["off_manifold"]
    specs = []
    xs = _spread(lo, hi, no, rng)
    levels = np.linspace(*W0_DECADES, max(no, 1))[rng.permutation(max(no, 1))]
    for j in range(no):
        g = int(np.argmin(np.sum((lin["xi"].T - xs[j]) ** 2, axis=1)))
        dirs = _directions(st, lin, g, rng)
        d = dirs[(j // 2) % len(dirs)]
        d = d / max(np.max(np.abs(d)), 1e-300)
        tail = np.r_[d, levels[j]] if w0_free else d
        if j % 2 == 0:
            specs.append(("free", True, np.r_[xs[j], tail]))
        else:
            specs.append(("greedy", True, np.r_[xs[j], 1.0, 0.0, 0.0, tail]))
    off = _runs(st, specs, disc, lin, "off_manifold")
    return Batch.concat([rand, man, sq, lin_runs, off])


def _refine(st: Setup, first: Batch, res: dict, budget: int, rng: np.random.Generator, lin: dict, disc: dict,
            progress: Callable[[float], None] | None = None) -> tuple[Batch, dict]:
    """(1 + lambda) evolution strategy from the best refinable runs: every generation one batch of perturbed
    parameter vectors for all seeds, the step shrinking by half per generation."""
    if budget <= 0:
        return _empty(st, 0, "refined", TABLE), None
    w0_free = not np.isfinite(st.w0_max)
    ratio = res["ratio_late"]   # a start that is tight by construction (ratio 1 at t = 0) is no lead
    refinable = np.array([p is not None for p in first.params])
    if not refinable.any():
        return _empty(st, 0, "refined", TABLE), None
    seeds = []
    zero = res["W0"] == 0
    for mask in (refinable & zero, refinable):
        if mask.any():
            cand = np.where(mask)[0]
            seeds.append(int(cand[np.argmax(ratio[cand])]))
    for i in np.argsort(-ratio):
        if len(set(seeds)) >= REFINE_SEEDS:
            break
        if refinable[i]:
            seeds.append(int(i))
    seeds = list(dict.fromkeys(seeds))
    best = {s: (float(ratio[s]), first.params[s][2].copy()) for s in seeds}
    gens = max(1, min(REFINE_GENERATIONS, budget // len(seeds)))
    batches, results = [], []
    used = 0
    for gen in range(gens):
        left = budget - used
        per = left // ((gens - gen) * len(seeds))
        extra = left - per * (gens - gen) * len(seeds) if gen == gens - 1 else 0
        specs, origin = [], []
        for j, s in enumerate(seeds):
            kind, off, _ = first.params[s]
            lo, hi = _param_bounds(st, kind, off, w0_free, disc)
            sigma = 0.2 * 0.5 ** gen * (hi - lo)
            count = per + (extra if j == 0 else 0)
            for _ in range(count):
                vec = np.clip(best[s][1] + sigma * rng.standard_normal(len(lo)), lo, hi)
                specs.append((kind, off, vec))
                origin.append(s)
        if not specs:
            continue
        b = _runs(st, specs, disc, lin, "refined")
        b.origin = np.array(origin)
        r = integrate(st, b, TOL)
        for i, s in enumerate(origin):
            if r["ratio_late"][i] > best[s][0]:
                best[s] = (float(r["ratio_late"][i]), b.params[i][2].copy())
        batches.append(b)
        results.append(r)
        used += len(b)
        if progress is not None:
            progress((gen + 1) / gens)
    if not batches:
        return _empty(st, 0, "refined", TABLE), None
    return Batch.concat(batches), _merge(results)


def _merge(results: list[dict]) -> dict:
    """The results of several batches as one (:func:`integrate`'s dicts, run after run).

    Parameters
    ----------
    results : list of dict
        Non-empty; ``largest_bound`` is maximised, ``steps`` summed, the per-run arrays concatenated.
    """
    out = {}
    for key in results[0]:
        if key == "largest_bound":
            out[key] = max(r[key] for r in results)
        elif key == "steps":
            out[key] = sum(r[key] for r in results)
        else:
            out[key] = np.concatenate([r[key] for r in results], axis=0)
    return out


def replay(st: Setup, batch: Batch, res: dict, idx: np.ndarray) -> Batch:
    """The runs idx with their held inputs as a table (the same v, no guard): for the verification.  The compiled
    runs keep no inputs: each is integrated again alone at :data:`TOL` (the same run, since its step control is
    its own) to recover them.

    Parameters
    ----------
    st : Setup
    batch : Batch
    res : dict
        :func:`integrate`'s result for ``batch``.
    idx : ndarray of int
        The runs.
    """
    b = batch.take(idx)
    held = (b.mode == TABLE) | (b.mode == GREEDY)
    # the inputs the runs held (integrate keeps none): run them again, recording them
    vused = st.loop.run(st, b, TOL, unit_candidates(st.model.m_hat), w0(st, b), DIVERGED, GUARD_LOOKAHEAD)["vused"]
    b.vtab = np.where(held[:, None, None], vused, b.vtab)
    b.mode = np.where(held, TABLE, b.mode)
    b.guard = np.zeros(len(b), dtype=bool)
    return b


def search(st: Setup, runs: int, rng: np.random.Generator, progress: Callable[[float], None] | None = None) -> tuple[Batch, dict, dict, dict]:
    """The search: the first batch over the strategies (:data:`SHARES`), integrated, then refined.

    Parameters
    ----------
    st : Setup
    runs : int
        Runs in all (the refinement's share included).
    rng : numpy Generator
    progress : callable, optional
        Called with the fraction done.

    Returns
    -------
    batch, res, counts, disc
        The runs, their results (:func:`integrate`), the runs per strategy and the discretised linearisation.
    """
    report = progress or (lambda frac: None)
    disc = discrete(st, st.lin)
    counts = _allocate(runs)
    first = _first_batch(st, counts, rng, st.lin, disc)
    res = integrate(st, first, TOL, progress=lambda frac: report(0.7 * frac))
    report(0.7)
    ref_b, ref_r = _refine(st, first, res, counts["refined"], rng, st.lin, disc, progress=lambda frac: report(0.7 + 0.3 * frac))
    if ref_r is None:
        return first, res, counts, disc
    return Batch.concat([first, ref_b]), _merge([res, ref_r]), counts, disc
