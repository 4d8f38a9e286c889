"""Error-aware planning (issue 45): a task's plan on one abstract state that carries the comparison state w of the
a-posteriori bound (docs/guaranteed.md, "Error-aware planning") and deflates the task's sets by sqrt(w(t) / alpha_h)
at each moment instead of by one uniform EPS.

Along any run of the interface, e = p(xi) - x and W = e^T M e obey (C): W' <= -(lambda - eps) W + (|L^T r| + a0)^2 /
eps, where r = dp/dxi delta v - g (u - l - K e) is what the interface does to the run and a0 = rho_bar + ebar w_max
collects what is always there (the fitted p's PDE residual, the disturbance at its bound).  Where the bound stage's
dbar is the q = 0 value (one input, ``saturate: scale`` or no saturation; a feedback design inside its region),
|L^T r| <= theta(xi) |v| with theta(xi) = ||L^T dp/dxi delta(xi)||, a function of xi alone: so a plan on the
abstraction can bound the plant's W without seeing the plant.  The plan holds v over each period of length tau;
over period j xi moves monotonically (one abstract state, a constant input) between its ends, theta is bounded over
the cells it crosses (:class:`ThetaTable`, proved in ball arithmetic per cell), and the comparison equation is solved
in closed form:

    w_(j+1) = B + (w_j - B) e^(-(lambda - eps) tau),   B = (theta_j |v_j| + a0)^2 / (eps (lambda - eps)),

monotone between w_j and w_(j+1) within the period.  W(t) <= w(t) at every t (Gronwall, as for the governor), so
|psi - y| <= sqrt(w(t) / alpha_h) (eq. (6)).  Each v_j is the set-point law scaled, as the governor scales it, so that
w stays below the level W_lim = alpha_h EPS^2 (capped by the region where the bound is certified): the plan is the
governor inside the plan, with theta(xi) in place of the measured r.  The plant runs the table of held inputs.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import sympy as sp

from ashc_cli.closedloop import rk
from ashc_cli.closedloop.task_monitor import robustness
from ashc_cli.closedloop.terms import DesignTerms, design_matrices
from ashc_cli.design.artefacts import Artefact
from ashc_cli.design.upstream import theta_is_pointwise
from ashc_cli.numerics import interval, proofs
from ashc_cli.numerics.proofs import PROVED, SAMPLED
from ashc_cli.problem.model import compile_flat

__all__ = ["ThetaTable", "Comparison", "theta_table", "build_theta_table", "comparison", "ErrorRun", "abstract_field", "run_plan", "certified_margin", "level_for", "fits",
           "reach_lower_bounds", "fitted_gain", "within_plan", "PLAN_PERIODS", "PLAN_SUB", "THETA_CELLS", "LEVEL_MARGIN", "S_MIN", "S_COARSE", "S_FINE"]

#: Periods of the plan over the task's horizon (the held table the plant runs has one input per period).
PLAN_PERIODS = 1000
#: RK4 steps per period (the abstraction under a held input is smooth).
PLAN_SUB = 5
#: Cells of V over which theta is bounded, one ball-arithmetic enclosure each.
THETA_CELLS = 1000
#: The plan keeps w below (1 - LEVEL_MARGIN) W_lim: room for the rounding of the closed-form steps.
LEVEL_MARGIN = 1e-9


@dataclass(frozen=True)
class ThetaTable:
    """An upper bound of theta(xi) = ||L^T dp/dxi delta(xi)|| over each cell of a uniform grid of V (one abstract
    state), or the bound stage's dbar where no local bound holds.

    Attributes
    ----------
    lo, eta : float
        V's lower end and the cell width.
    theta : ndarray (cells,)
    dbar : float
        The bound stage's dbar (taken outside V and where a cell's enclosure is not finite).
    how : str
        How the table was made (for the artefact and the docs).
    evidence : str
        ``proved`` when every cell's bound is a ball-arithmetic enclosure; else ``sampled`` (dbar's evidence).
    """

    lo: float
    eta: float
    theta: np.ndarray
    dbar: float
    how: str
    evidence: str

    def over_many(self, a: np.ndarray, b: np.ndarray) -> np.ndarray:
        """:meth:`over` of each pair (a_i, b_i) at once (a sparse table of maxima over ranges of cells; dbar where a pair
        is not finite or its widened range leaves V by more than the one cell of widening)."""
        a, b = np.asarray(a, dtype=float), np.asarray(b, dtype=float)
        n = self.theta.size
        out = np.full(a.shape, self.dbar)
        lo, hi = np.minimum(a, b), np.maximum(a, b)
        good = np.isfinite(lo) & np.isfinite(hi)
        with np.errstate(invalid="ignore"):
            i = np.where(good, np.floor((lo - self.lo) / self.eta), 0).astype(np.int64) - 1
            k = np.where(good, np.floor((hi - self.lo) / self.eta), 0).astype(np.int64) + 1
        good &= (i >= -1) & (k <= n)
        i, k = np.clip(i, 0, n - 1), np.clip(k, 0, n - 1)
        levels = self._levels()
        span = k - i + 1
        lev = np.floor(np.log2(np.maximum(span, 1))).astype(np.int64)
        for L in np.unique(lev[good]):
            sel = good & (lev == L)
            table = levels[L]
            out[sel] = np.maximum(table[i[sel]], table[k[sel] + 1 - (1 << L)])
        return out

    def _levels(self) -> list:
        """The sparse table: level L holds the maxima over 2^L consecutive cells."""
        if not hasattr(self, "_cache"):
            levels, width = [np.asarray(self.theta, dtype=float)], 1
            while 2 * width <= self.theta.size:
                levels.append(np.maximum(levels[-1][:-width], levels[-1][width:]))
                width *= 2
            object.__setattr__(self, "_cache", levels)
        return self._cache

    def over(self, a: float, b: float) -> float:
        """The largest bound over the cells that meet [a, b] widened by a cell each side (the RK4 ends of a period are
        within far less of the exact flow's); dbar when that leaves V.

        Parameters
        ----------
        a, b : float

        Returns
        -------
        float
        """
        return float(self.over_many(np.array([a], dtype=float), np.array([b], dtype=float))[0])


@dataclass(frozen=True)
class Comparison:
    """The comparison equation of the a-posteriori bound, w' = -a w + (theta |v| + a0)^2 / eps with a = lambda - eps,
    and the region where it is certified.

    Attributes
    ----------
    a, eps, alpha_h : float
        lambda - eps, eps and alpha_h of the bound stage.
    a0 : float
        rho_bar + ebar w_max: the fitted p's residual and the disturbance at its bound (0 without either).
    w_cap, v_cap : float
        w0_max_certified and v_max_certified (with the disturbance's share when there is one): inf for a global bound.
    """

    a: float
    eps: float
    alpha_h: float
    a0: float
    w_cap: float
    v_cap: float

    def step(self, w0: float, theta: float, v: float, tau: float) -> float:
        """w at the end of a period of length tau from w0, with |L^T r| <= theta |v| throughout (rounded up)."""
        B = (theta * abs(v) + self.a0) ** 2 / (self.eps * self.a)
        E = np.exp(-self.a * tau)
        return float((B + (w0 - B) * E) * (1 + 1e-12) + 1e-300)

    def room(self, w0: float, theta: float, tau: float, level: float) -> float:
        """The largest |v| with :meth:`step` <= level (0 when even v = 0 overshoots; inf when theta = 0)."""
        E = np.exp(-self.a * tau)
        B_max = (level * (1 - 1e-12) - w0 * E) / (1 - E)
        reach = np.sqrt(max(B_max, 0.0) * self.eps * self.a) - self.a0
        if reach <= 0:
            return 0.0
        return float(reach / theta * (1 - 1e-12)) if theta > 0 else np.inf

    def room_many(self, w0: float, theta: np.ndarray, tau: float, level: float) -> np.ndarray:
        """:meth:`room` for each theta at once."""
        E = np.exp(-self.a * tau)
        B_max = (level * (1 - 1e-12) - w0 * E) / (1 - E)
        reach = np.sqrt(max(B_max, 0.0) * self.eps * self.a) - self.a0
        theta = np.asarray(theta, dtype=float)
        if reach <= 0:
            return np.zeros(theta.shape)
        with np.errstate(divide="ignore"):
            return np.where(theta > 0, reach / np.where(theta > 0, theta, 1.0) * (1 - 1e-12), np.inf)

    def deflation(self, w: np.ndarray) -> np.ndarray:
        """sqrt(w / alpha_h): what |psi - y| may be where W <= w (eq. (6))."""
        return np.sqrt(np.maximum(np.asarray(w, dtype=float), 0.0) / self.alpha_h)


def comparison(up: dict[str, Artefact]) -> Comparison:
    """The :class:`Comparison` of a design (its bound stage).

    Parameters
    ----------
    up : dict of str to Artefact

    Returns
    -------
    Comparison
    """
    bd = up["bound"].values
    lam, eps = float(bd["lambda"]), float(bd["epsilon"])
    a0 = float(bd.get("rho_bar", 0.0)) + float(bd.get("ebar", 0.0)) * float(bd.get("w_max", 0.0))
    v_cap = float(bd.get("v_max_certified_with_w", bd.get("v_max_certified", np.inf))) if "disturbance_term" in bd else float(bd.get("v_max_certified", np.inf))
    return Comparison(lam - eps, eps, float(bd["alpha_h"]), a0, float(bd.get("w0_max_certified", np.inf)), v_cap)


#: Tables already built in this process, by (bound artefact, cells): a plan, its fallback and synthesize's lower bound
#: read the same one (at hundreds of states a table takes a minute of ball arithmetic).
_TABLES: dict = {}


def theta_table(model, up: dict[str, Artefact], cells: int = THETA_CELLS) -> ThetaTable:
    """:func:`build_theta_table`, kept per bound artefact (by its sha256, once it was read or written).

    Parameters
    ----------
    model : Model
    up : dict of str to Artefact
    cells : int

    Returns
    -------
    ThetaTable
    """
    sha = up["bound"].provenance.get("sha256")
    if not sha:                 # an artefact never written has no name to keep its table by
        return build_theta_table(model, up, cells)
    key = (sha, cells, tuple(np.asarray(model.V, dtype=float).ravel()))
    if key not in _TABLES:
        if len(_TABLES) >= 8:
            _TABLES.clear()
        _TABLES[key] = build_theta_table(model, up, cells)
    return _TABLES[key]


def build_theta_table(model, up: dict[str, Artefact], cells: int = THETA_CELLS) -> ThetaTable:
    """:class:`ThetaTable` of a design with one abstract state.

    theta bounds |L^T r| / |v| pointwise only where :func:`ashc_cli.design.upstream.theta_is_pointwise` says so (the
    bound stage's rule for dbar = dbar_q0).  Otherwise (several inputs clipped channel by channel) the table is dbar
    on every cell.  Each cell's bound is the upper end of a ball-arithmetic enclosure of
    ||sqrt(M) dp/dxi delta|| over it (natural and mean-value forms), capped by dbar where dbar is proved.

    Parameters
    ----------
    model : Model
    up : dict of str to Artefact
    cells : int

    Returns
    -------
    ThetaTable
    """
    bd = up["bound"].values
    V = np.asarray(model.V, dtype=float)
    lo, hi = float(V[0, 0]), float(V[0, 1])
    eta = (hi - lo) / cells
    dbar = float(bd["dbar"])
    dbar_proved = str(bd.get("evidence_dbar", SAMPLED)) == PROVED

    def flat(why: str) -> ThetaTable:
        return ThetaTable(lo, eta, np.full(cells, dbar), dbar, f"dbar on every cell ({why})", PROVED if dbar_proved else SAMPLED)

    if not theta_is_pointwise(model):
        # several inputs clipped channel by channel: a clipping pattern's theta can exceed the q = 0 value, even where the
        # bound stage's dbar (their sup, at least dbar_q0) equals dbar_q0 (found by an attack: 2.2 times at some xi)
        return flat("the interface's clipping patterns of several inputs: theta depends on x too")
    M = np.asarray(up["bound"].value("M"), dtype=float)
    try:
        # the squared norm (the outer root taken on its upper end): a root of an enclosure that reaches below 0 would be nan
        norm = proofs.norm_expr(M, up["bound"].expr("dp_delta"))
        squared = norm.base if norm.is_Pow and norm.exp == sp.Rational(1, 2) else norm ** 2      # a constant norm is a number
        fun = proofs.compile_claims(model, [squared], list(model.xi))
    except (interval.UnsupportedExpression, ValueError):
        return flat("||sqrt(M) dp/dxi delta|| cannot be enclosed in ball arithmetic")
    edges = lo + eta * np.arange(cells + 1)
    edges[-1] = hi
    sampled = model.numeric(sp.Matrix([[squared]]), list(model.xi))
    squared = np.array([_refined_upper(fun, sampled, edges[i], edges[i + 1], REFINE_DEPTH) for i in range(cells)], dtype=float)
    out = np.nextafter(np.sqrt(np.maximum(squared, 0.0)), np.inf)
    finite = np.isfinite(out)
    theta = np.where(finite, out, dbar)
    if dbar_proved:
        theta = np.minimum(theta, dbar)
    evidence = PROVED if finite.all() else (PROVED if dbar_proved else SAMPLED)
    return ThetaTable(lo, eta, theta, dbar, f"||sqrt(M) dp/dxi delta|| enclosed in ball arithmetic on each of {cells} cells of V "
                      f"({int(finite.sum())} finite; dbar elsewhere)", evidence)


#: A cell whose enclosure is more than REFINE_SLACK above theta^2 sampled at its ends and centre is cut in REFINE_SPLIT
#: pieces, down to REFINE_DEPTH times (the mean-value form tightens on narrower boxes where terms cancel).
REFINE_SLACK, REFINE_SPLIT, REFINE_DEPTH = 0.02, 4, 2


def _refined_upper(fun, sampled, a: float, b: float, depth: int) -> float:
    """An upper bound of the squared norm over [a, b]: the enclosure's upper end, or the largest over REFINE_SPLIT
    pieces where it is loose (still an upper bound: the pieces cover [a, b])."""
    upper = interval.enclose(fun, np.array([[a, b]]))[0][1]
    if depth == 0 or not np.isfinite(upper):
        return upper
    seen = float(np.max(np.ravel(sampled(np.array([a, 0.5 * (a + b), b])))))
    if upper <= seen * (1 + REFINE_SLACK) + 1e-300:
        return upper
    cuts = np.linspace(a, b, REFINE_SPLIT + 1)
    cuts[-1] = b
    return min(upper, max(_refined_upper(fun, sampled, cuts[k], cuts[k + 1], depth - 1) for k in range(REFINE_SPLIT)))


@dataclass
class ErrorRun:
    """An error-aware plan on the abstraction, at one level.

    Attributes
    ----------
    t, xi, psi, v, w : ndarray
        On the plan's RK4 grid: (N,), (1, N), (p, N), (1, N), (N,); w is the comparison bound at each sample.
    deflation : ndarray (N,)
        sqrt(w / alpha_h) at each sample, the largest over its two neighbouring intervals (w is monotone within a
        period).
    inputs : ndarray (periods,)
        The held input of each period.
    switches : list of float
        When the plan aims at each reach set.
    tau : float
        The period.
    """

    t: np.ndarray
    xi: np.ndarray
    psi: np.ndarray
    v: np.ndarray
    w: np.ndarray
    deflation: np.ndarray
    inputs: np.ndarray
    switches: list
    tau: float


def run_plan(model, plant: DesignTerms, field, xi0: np.ndarray, w0: float, refs: list, gain: float, level: float, table: ThetaTable,
             comp: Comparison) -> ErrorRun:
    """The plan at one level: per period the set-point law aimed at the current reach set's reference, scaled so
    that the comparison bound stays below ``level``, held; the reach sets switched once psi has held the current one
    deflated by sqrt(w / alpha_h) for its hold.

    Parameters
    ----------
    model : Model
        One abstract state, with a task.
    plant : DesignTerms
    field : callable
        (xi, v) -> phi_bar(xi) + delta(xi) v on arrays (:func:`abstract_field`), for the batches of trial inputs.
    xi0 : ndarray (1,)
    w0 : float
        The comparison state at the start (W(xi0, x0)).
    refs : list of ndarray (1,)
        The reach sets' reference states.
    gain : float
        The set-point gain (the law's gain is min(gain, 1 / tau): a held input that would overshoot the reference
        within a period is not asked for).
    level : float
        w stays <= level.
    table : ThetaTable
    comp : Comparison

    Returns
    -------
    ErrorRun
    """
    task = model.spec.task
    P, sub = PLAN_PERIODS, PLAN_SUB
    tau = task.horizon / P
    h = tau / sub
    N = P * sub + 1
    t = np.linspace(0.0, task.horizon, N)
    xi, psi, v_run, w_run = np.empty((1, N)), np.empty((model.p, N)), np.empty((1, N)), np.empty(N)
    inputs = np.empty(P)
    g_eff = min(float(gain), 1.0 / tau)
    z, w = np.array(xi0, dtype=float), float(w0)
    k, entered, switches = 0, None, [0.0]
    offsets = np.arange(sub) * h

    def flow(z0, v, record_from=None):
        f = lambda y: (lambda a: a[0][:, 0] + a[1][:, 0] * v)(plant.abstraction(y))     # noqa: E731
        y = z0
        for s in range(sub):
            phi, delta, kap = plant.abstraction(y)
            if record_from is not None:
                xi[:, record_from + s], psi[:, record_from + s] = y, kap[:, 0]
            y = rk.fixed_step(f, y, h, phi[:, 0] + delta[:, 0] * v)
        return y

    for j in range(P):
        ref = refs[min(k, len(refs) - 1)]
        phi, delta, _ = plant.abstraction(z)
        v_sp = float((g_eff * (ref[0] - z[0]) - phi[0, 0]) / delta[0, 0])
        v_sp = float(np.clip(v_sp, -comp.v_cap, comp.v_cap))
        theta, v = _period_input(field, z, v_sp, w, (h, sub), level, table, comp)
        end = flow(z, v, record_from=j * sub)
        B = (theta * abs(v) + comp.a0) ** 2 / (comp.eps * comp.a)
        w_run[j * sub:(j + 1) * sub] = B + (w - B) * np.exp(-comp.a * offsets)
        v_run[:, j * sub:(j + 1) * sub] = v
        inputs[j] = v
        w = comp.step(w, theta, v, tau)
        z = end
        if k < len(refs) - 1:           # switch at the period's end once the current set has been held, deflated
            box = np.asarray(task.reach[k].set, dtype=float)
            for i in range(j * sub, (j + 1) * sub):
                d = comp.deflation(w_run[i])
                inside = bool(np.all(psi[:, i] >= box[:, 0] + d) and np.all(psi[:, i] <= box[:, 1] - d))
                entered = (t[i] if entered is None else entered) if inside else None
            if entered is not None and t[(j + 1) * sub] - entered >= task.reach[k].hold:
                k, entered = k + 1, None
                switches.append(float(t[(j + 1) * sub]))
    phi, delta, kap = plant.abstraction(z)
    xi[:, -1], psi[:, -1], v_run[:, -1], w_run[-1] = z, kap[:, 0], v_run[:, -2], w
    wide = np.maximum(w_run, np.maximum(np.r_[w_run[1:], w_run[-1]], np.r_[w_run[0], w_run[:-1]]))
    return ErrorRun(t, xi, psi, v_run, w_run, comp.deflation(wide), inputs, switches, tau)


def abstract_field(model, up: dict[str, Artefact]):
    """(xi, v) -> phi_bar(xi) + delta(xi) v on arrays of one abstract state (a batch of trial inputs at once).

    Parameters
    ----------
    model : Model
    up : dict of str to Artefact

    Returns
    -------
    callable
    """
    T = design_matrices(model, up, ("phi", "delta"))
    fun = compile_flat([T["phi"][0, 0], T["delta"][0, 0]], list(model.xi), model.values)

    def field(x: np.ndarray, v: np.ndarray) -> np.ndarray:
        phi, delta = fun(x)
        return phi + delta * v
    return field


def _period_input(field, z: np.ndarray, v_sp: float, w: float, steps: tuple, level: float, table: ThetaTable,
                  comp: Comparison) -> tuple[float, float]:
    """(theta, v) of one period: v = s v_sp with the largest s in [0, 1] whose period leaves room for it, theta the
    bound over that period's path.

    The path of a held v lies between the period's start and its end; for s v_sp, s in [0, 1], between the start and
    the ends for 0 and for s (a scalar flow is monotone in time and, delta of one sign on V, in the held input).  The
    window grows with s, so its theta does and the room (:meth:`Comparison.room`) shrinks: the admissible s form an
    interval from 0, found on S_COARSE geometric trial scales, then S_FINE between the last admissible and the next,
    each batch integrated at once (RK4, the plan's substeps)."""
    h, sub = steps
    tau = h * sub

    def judge(scales: np.ndarray):
        vs = scales * v_sp
        x = np.full(vs.shape, float(z[0]))
        with np.errstate(over="ignore", invalid="ignore"):      # a trial that throws xi out of V ends in inf: dbar there
            for _ in range(sub):
                x = rk.fixed_step(lambda y: field(y, vs), x, h, field(x, vs))
        lo, hi = np.minimum(np.minimum(x, x[0]), z[0]), np.maximum(np.maximum(x, x[0]), z[0])
        thetas = table.over_many(lo, hi)
        ok = np.abs(vs) <= comp.room_many(w, thetas, tau, level)
        return thetas, ok

    coarse = np.r_[0.0, np.geomspace(S_MIN, 1.0, S_COARSE)]     # scale 0 first: the ends of v = 0 for every window
    thetas, ok = judge(coarse)
    i = int(np.flatnonzero(ok).max())       # s = 0 is admissible (room >= 0)
    if i + 1 < coarse.size:
        fine = np.r_[0.0, np.linspace(coarse[i], coarse[i + 1], S_FINE + 2)[1:-1]]
        th_f, ok_f = judge(fine)
        k = int(np.flatnonzero(ok_f).max())
        if k > 0 and fine[k] > coarse[i]:
            return float(th_f[k]), float(fine[k] * v_sp)
    return float(thetas[i]), float(coarse[i] * v_sp)


#: A period's input: S_COARSE trial scales of the set-point law's, geometric from S_MIN to 1, then S_FINE between the
#: largest admissible and the next.
S_MIN, S_COARSE, S_FINE = 1e-6, 24, 16


def certified_margin(model, run: ErrorRun) -> tuple[float, float, object, bool]:
    """psi's robustness on the plan against the sets deflated by sqrt(w / alpha_h) at each sample, less the sampling
    margin (max |dpsi| between samples); -inf if xi leaves V.

    Parameters
    ----------
    model : Model
    run : ErrorRun

    Returns
    -------
    certified, margin : float
    rob : TaskRobustness
        psi's robustness with the deflation (its parts).
    in_V : bool
    """
    margin = float(np.abs(np.diff(run.psi, axis=1)).max()) if run.t.size > 1 else 0.0
    rob = robustness(model.spec.task, run.t, run.psi, margin=run.deflation)
    in_V = bool(np.all((run.xi >= model.V[:, :1] - 1e-12) & (run.xi <= model.V[:, 1:] + 1e-12)))
    return (float(rob.robustness - margin) if in_V else -np.inf), margin, rob, in_V


def level_for(tolerance: float, comp: Comparison) -> float:
    """W_lim for a tolerance EPS: alpha_h EPS^2, capped by the region where the bound is certified, less LEVEL_MARGIN.

    Parameters
    ----------
    tolerance : float
    comp : Comparison

    Returns
    -------
    float
    """
    return float(min(comp.alpha_h * tolerance ** 2, comp.w_cap) * (1 - LEVEL_MARGIN))


def fits(level: float, w0: float, comp: Comparison) -> bool:
    """Whether a plan at ``level`` can start: w0 below it, and v = 0 keeps w below it (a0^2 / (eps a) < level).

    Parameters
    ----------
    level, w0 : float
    comp : Comparison

    Returns
    -------
    bool
    """
    return w0 < level and comp.a0 ** 2 / (comp.eps * comp.a) < level



def fitted_gain(model, up: dict[str, Artefact], xi0: np.ndarray, refs: list) -> tuple | None:
    """The budget's gain fitted to the task: G with dbar over the part of V between the start and the reach sets'
    references (the set-point law aimed at them keeps xi there when phi_bar = 0), from theta's proved table
    (:func:`theta_table`: each cell's bound, a cell more each side).

    Parameters
    ----------
    model : Model
    up : dict of str to Artefact
    xi0 : ndarray (1,)
    refs : list of ndarray (1,)
        The reach sets' references (:func:`ashc_cli.design.task_plan.reach_references`).

    Returns
    -------
    tuple or None
        (G, lo, hi); None with a drift (phi_bar != 0) or where that G is no smaller than the bound stage's.
    """
    bd = up["bound"].values
    dbar, G = float(bd["dbar"]), float(bd["gain"])
    if any(e != 0 for e in design_matrices(model, up, ("phi",))["phi"]):        # a drift can carry xi past the references
        return None
    table = theta_table(model, up)
    points = [float(xi0[0])] + [float(r[0]) for r in refs]
    lo, hi = max(min(points), table.lo), min(max(points), table.lo + table.eta * table.theta.size)
    local = table.over(lo, hi)
    if not (dbar > 0 and local < dbar):
        return None
    return G * local / dbar, lo, hi


def within_plan(plan, values: dict) -> bool:
    """Whether a plant run of an error-aware plan keeps to the plan's claim (docs/guaranteed.md): its own comparison w
    nowhere above the plan's bound (to 1e-9 of the level) and its xi within a cell of theta's table of the plan's.

    Parameters
    ----------
    plan : TaskPlan
        Error-aware (its ``w_level`` and ``theta_cell`` are read).
    values : dict
        Of :func:`ashc_cli.design.task_plan.on_the_plant` (``w_over_plan``, ``xi_deviation``).

    Returns
    -------
    bool
    """
    return bool(values["w_over_plan"] <= 1e-9 * max(plan.w_level, 1.0) and values["xi_deviation"] <= plan.theta_cell)


def reach_lower_bounds(model, up: dict[str, Artefact], table: ThetaTable, comp: Comparison, level: float, xi0: np.ndarray) -> np.ndarray:
    """Per reach set, a time before which psi cannot enter it under any abstract input whose comparison bound stays below
    ``level`` (every plan certified at EPS = sqrt(level / alpha_h) by this bound: the error-aware plans, and the budget's,
    whose |v| <= v_max keeps (theta |v|)^2 / (eps a) <= alpha_h EPS^2), the reach sets met in order.

    With phi_bar = 0, zeta(xi) = integral of theta(s) / |delta(s)| ds grows along a run at most as theta |v|, and over any
    window of length s, (integral of theta |v|)^2 <= s integral of theta^2 v^2 <= s e^(a s) eps w <= s e^(a s) eps level
    (Cauchy-Schwarz, and w >= the integral of e^(-a (t - r)) theta^2 v^2 / eps); so zeta moves at most ceil(T / s) D(s) in
    a time T, D(s) = sqrt(s e^(a s) eps level), for every s.  With |v| <= v_max_certified as well, xi moves at most
    |delta| v_max_certified.  Leg k runs from where leg k - 1's set is nearest (after its hold) to set k; the bounds add.
    theta and delta are taken on the table's cells (theta the cell's bound, delta at its centre).

    Parameters
    ----------
    model : Model
        One abstract state, with a task.
    up : dict of str to Artefact
    table : ThetaTable
    comp : Comparison
    level : float
    xi0 : ndarray (1,)

    Returns
    -------
    ndarray (reaches,)
        Seconds from the start; NaN where phi_bar is not 0 on V (a drift moves xi for free) or a set has no cell.
    """
    task = model.spec.task
    n = table.theta.size
    centres = table.lo + table.eta * (np.arange(n) + 0.5)
    T = design_matrices(model, up, ("phi", "delta", "kappa"))
    phi, delta, kappa = (_on_cells(model.numeric(T[k], list(model.xi))(centres), n) for k in ("phi", "delta", "kappa"))
    out = np.full(len(task.reach), np.nan)
    if np.any(np.abs(np.ravel(phi)) > 0):
        return out
    speed = np.abs(delta[0, 0])
    zeta = np.r_[0.0, np.cumsum(table.theta / speed * table.eta)]         # at the cells' edges
    xi_len = np.r_[0.0, np.cumsum(np.full(n, table.eta) / (speed * comp.v_cap))] if np.isfinite(comp.v_cap) else None
    psi = kappa[:, 0, :]
    at = int(np.clip(np.floor((float(xi0[0]) - table.lo) / table.eta), 0, n - 1))
    here, now = np.array([at]), 0.0
    for k, r in enumerate(task.reach):
        box = np.asarray(r.set, dtype=float)
        inside = np.flatnonzero(np.all((psi >= box[:, :1]) & (psi <= box[:, 1:]), axis=0))
        if inside.size == 0:
            return out
        need = min(max(_time_for(_between(zeta, i, inside), comp, level), _between(xi_len, i, inside) if xi_len is not None else 0.0)
                   for i in here)
        now += need
        out[k] = now
        here, now = inside[[0, -1]], now + r.hold
    return out


def _on_cells(values, n: int) -> np.ndarray:
    """A compiled matrix's values at n points as (rows, cols, n) (a constant entry comes back without the points' axis)."""
    arr = np.asarray(values, dtype=float)
    return np.broadcast_to(arr if arr.ndim == 3 and arr.shape[-1] == n else arr.reshape(arr.shape[:2] + (1,)), arr.shape[:2] + (n,))


def _between(cum: np.ndarray, i: int, cells: np.ndarray) -> float:
    """The distance (by the cumulative measure ``cum`` at the cells' edges) from cell i to the nearest of ``cells``, edge
    to edge: 0 when i is one of them (no more than the distance between any of their points)."""
    lo, hi = int(cells.min()), int(cells.max())
    if i < lo:
        return float(cum[lo] - cum[i + 1])
    if i > hi:
        return float(cum[i] - cum[hi + 1])
    return 0.0


def _time_for(distance: float, comp: Comparison, level: float) -> float:
    """The least T with distance <= min over s of ceil(T / s) D(s), D(s) = sqrt(s e^(a s) eps level) (bisection)."""
    if distance <= 0:
        return 0.0
    s = np.geomspace(1e-4, 20.0, 400) / comp.a
    D = np.sqrt(s * np.exp(comp.a * s) * comp.eps * level)
    reach = lambda T: float(np.min(np.ceil(T / s) * D))      # noqa: E731 (nondecreasing in T)
    lo, hi = 0.0, 1.0
    while reach(hi) < distance:
        hi *= 2.0
    for _ in range(60):
        mid = 0.5 * (lo + hi)
        lo, hi = (mid, hi) if reach(mid) < distance else (lo, mid)
    return lo
