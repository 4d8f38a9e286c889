"""Rigorous bounds over boxes by branch and bound on compiled interval functions (:mod:`ashc_cli.numerics.interval`):
an upper bound on the supremum of a function over a box (:func:`sup_on_box`), a lower bound on its infimum
(:func:`inf_on_box`), its sign on a box (:func:`prove_positive`); and bounds on matrices: positive definiteness of a
float matrix (:func:`psd_lower_bound`, :func:`prove_psd`) and the largest eigenvalue of an interval matrix
(:func:`lambda_max_upper`).  A bound this module calls rigorous truly holds for the exact real numbers, whatever the
rounding.  The searches intersect the natural enclosure with the mean-value form f(c) + sum_i G_i (X_i - c_i), whose
overestimate shrinks with the square of the box width: tight tolerances are reached in a few thousand boxes.

Every search is bounded by work, never by the clock: a budget of boxes (``max_boxes``; by default the one
:func:`work_budget` sets for the stage being computed, from the spec key ``proofs.max_boxes``), so the same spec
gives the same bounds on an idle machine and on a loaded one.  :class:`ProofWork` adds up what the searches of one
stage spent and which of them spent their whole budget short of their tolerance.
"""

from __future__ import annotations

import contextlib
import contextvars
import heapq
import math
from collections.abc import Iterator, Sequence
from dataclasses import dataclass

import numpy as np
from flint import arb, arb_mat

from ashc_cli.errors import NumericalError
from ashc_cli.numerics.interval import IntervalFunction
from ashc_cli.numerics._infsup import (INF, ZERO, ball_of, centre, check_box, fdn, from_ball, fup, iv_neg, midpoint)

__all__ = ["MAX_BOXES", "ProofWork", "work_budget", "box_budget", "SupResult", "InfResult", "sup_on_box", "inf_on_box", "prove_positive", "psd_lower_bound", "prove_psd", "lambda_max_upper"]


#: Boxes one sup, inf or sign search may enclose unless the spec says otherwise (``proofs.max_boxes``).
MAX_BOXES = 20000


@dataclass
class ProofWork:
    """The branch-and-bound work of one stage: recorded in its artefact (``meta["proof_work"]``).

    Attributes
    ----------
    max_boxes : int
        The budget of one search (``proofs.max_boxes``).
    searches : int
        Searches run.
    boxes : int
        Boxes enclosed, summed over the searches.
    spent : int
        Searches that used their whole budget before reaching their tolerance (their claims stay "sampled", or
        their bound is looser than the tolerance asked).
    largest_gap : float
        The widest ``upper - lower`` left by such a search (inf when an enclosure stayed unbounded).
    """

    max_boxes: int = MAX_BOXES
    searches: int = 0
    boxes: int = 0
    spent: int = 0
    largest_gap: float = 0.0

    def record(self, boxes: int, budget: int, proved: bool, gap: float) -> None:
        """Add one search: the boxes it enclosed, its budget, whether it reached its tolerance, its final gap."""
        self.searches += 1
        self.boxes += boxes
        if not proved and boxes >= budget:
            self.spent += 1
            self.largest_gap = max(self.largest_gap, gap if math.isfinite(gap) else math.inf)

    def as_meta(self) -> dict:
        """The record as JSON-able facts (an unbounded gap as the string "inf")."""
        gap = self.largest_gap if math.isfinite(self.largest_gap) else "inf"
        return {"max_boxes": self.max_boxes, "searches": self.searches, "boxes": self.boxes, "budget_spent": self.spent,
                "largest_gap": gap}

    def line(self) -> str:
        """One line for the stage's report when a search spent its budget, else ""."""
        if not self.spent:
            return ""
        return (f"box budget {self.max_boxes} spent in {self.spent} of {self.searches} searches (largest gap "
                f"{self.largest_gap:.3g}): the claims they serve are sampled or looser; raise proofs.max_boxes")


_WORK: contextvars.ContextVar[ProofWork | None] = contextvars.ContextVar("ashc_proof_work", default=None)


@contextlib.contextmanager
def work_budget(max_boxes: int = MAX_BOXES) -> Iterator[ProofWork]:
    """Within the block, searches default to ``max_boxes`` boxes and report their work to the yielded record.

    Parameters
    ----------
    max_boxes : int
        The budget of one search (the spec's ``proofs.max_boxes``).

    Yields
    ------
    ProofWork
        What the searches in the block spent.
    """
    if int(max_boxes) < 1:
        raise ValueError(f"max_boxes must be >= 1, got {max_boxes}")
    token = _WORK.set(ProofWork(max_boxes=int(max_boxes)))
    try:
        yield _WORK.get()
    finally:
        _WORK.reset(token)


def box_budget(share: float = 1.0) -> int:
    """The budget of one search: ``share`` of the current :func:`work_budget` (:data:`MAX_BOXES` outside one).

    Parameters
    ----------
    share : float
        The fraction wanted (a refinement that runs many small searches asks for less than a whole budget).

    Returns
    -------
    int
        At least 1.
    """
    work = _WORK.get()
    return max(1, int((work.max_boxes if work is not None else MAX_BOXES) * share))


def _record(boxes: int, budget: int, proved: bool, gap: float) -> None:
    work = _WORK.get()
    if work is not None:
        work.record(boxes, budget, proved, gap)


class _Evaluator:
    """Evaluates one output of a function on float boxes and points, as intervals (maybe negated)."""

    def __init__(self, fun, index: int, negate: bool, d: int):
        self.fun = fun
        self.index = index
        self.negate = negate
        self.compiled = isinstance(fun, IntervalFunction)
        if self.compiled:
            if not 0 <= index < len(fun):
                raise ValueError(f"index {index} out of range for {len(fun)} outputs")
            if fun.n_in != d:
                raise ValueError(f"box has {d} rows, the function takes {fun.n_in} arguments")

    def _sign(self, a):
        return iv_neg(a) if (self.negate and a is not None) else a

    def box(self, lo: list[float], hi: list[float], c: list[float]):
        """Evaluate on a box: ``(enc, fc, smear, up)``.

        ``enc`` encloses the function on the box and ``fc`` at the point ``c`` (intervals or None);
        ``smear[k]`` bounds how much the function can change along dimension k on the box
        (|df/dx_k| * width_k) and ``up[k]`` is the sign of df/dx_k where it is known (0 where not);
        both None without a finite gradient enclosure (e.g. for a plain callable).
        """
        if not self.compiled:
            enc = from_ball(self.fun([ball_of(a, b) for a, b in zip(lo, hi)])[self.index])
            return self._sign(enc), self.point(c), None, None
        encs, at_c, grads = self.fun.enclose_box(lo, hi, c, (self.index,))
        enc, g = encs[0], grads[0]
        smear = up = None
        if enc is not None and isinstance(g, list):
            smear = [max(-fdn(gk[0]), fup(gk[1])) * (b - a) for gk, a, b in zip(g, lo, hi)]
            sgn = -1 if self.negate else 1
            up = [sgn if gk[0] > ZERO else -sgn if gk[1] < ZERO else 0 for gk in g]
        return self._sign(enc), self._sign(at_c[0]), smear, up

    def point(self, x: Sequence[float]):
        if self.compiled:
            a = [(arb(v),) * 2 for v in x]
            return self._sign(self.fun.eval_intervals(a, (self.index,))[0])
        return self._sign(from_ball(self.fun([arb(float(v)) for v in x])[self.index]))


def _widest(lo: list[float], hi: list[float], scale: list[float], smear: list[float] | None = None) -> tuple[int, float] | None:
    """The dimension to bisect and its split point, if any.

    With a gradient enclosure, the dimension along which the function may change most (largest
    smear |df/dx_k| * width_k: dimensions the function does not depend on are never split);
    otherwise, or to break ties, the widest relative to the original box.
    """
    if smear is not None and max(smear, default=0.0) > 0.0:
        order = sorted(range(len(lo)), key=lambda k: (-smear[k], -(hi[k] - lo[k]) / scale[k]))
    else:
        order = sorted(range(len(lo)), key=lambda k: -(hi[k] - lo[k]) / scale[k])
    for k in order:
        a, b = lo[k], hi[k]
        m = midpoint(a, b)
        if a < m < b:
            return k, m
    return None


def _toward(lo: list[float], hi: list[float], c: list[float], direction: list[int]) -> list[float]:
    """The point of the box at c moved to the upper/lower face wherever direction is +1/-1."""
    return [b if s > 0 else a if s < 0 else m for a, b, m, s in zip(lo, hi, c, direction)]


# --- suprema and infima ---------------------------------------------------------------------------------


@dataclass(frozen=True)
class SupResult:
    """Result of :func:`sup_on_box`.

    Attributes
    ----------
    upper : float
        A rigorous upper bound of sup_box f (``inf`` if the enclosure stayed non-finite somewhere).
    lower : float
        A value f is proved to reach or exceed at ``argmax`` (the lower end of an arb enclosure of f
        there), so ``lower <= sup_box f``; ``-inf`` if no point evaluation was finite.
    argmax : ndarray, shape (d,)
        The point where ``lower`` was found (nan if none).
    boxes : int
        Number of boxes evaluated.
    proved : bool
        Whether ``upper`` is finite and ``upper - lower <= rtol*|lower| + atol``.
    """

    upper: float
    lower: float
    argmax: np.ndarray
    boxes: int
    proved: bool


@dataclass(frozen=True)
class InfResult:
    """Result of :func:`inf_on_box`.

    Attributes
    ----------
    lower : float
        A rigorous lower bound of inf_box f (``-inf`` if the enclosure stayed non-finite somewhere).
    upper : float
        A value f is proved to reach or fall below at ``argmin`` (the upper end of an arb enclosure of f
        there), so ``upper >= inf_box f``; ``inf`` if no point evaluation was finite.
    argmin : ndarray, shape (d,)
        The point where ``upper`` was found (nan if none).
    boxes : int
        Number of boxes evaluated.
    proved : bool
        Whether ``lower`` is finite and ``upper - lower <= rtol*|upper| + atol``.
    """

    lower: float
    upper: float
    argmin: np.ndarray
    boxes: int
    proved: bool


def _branch_and_bound(fun, box, index, negate, rtol, atol, max_boxes, seeds):
    """Maximise output ``index`` of fun (of -fun when negate); returns (upper, lower, argmax, boxes, proved)."""
    lo0, hi0 = check_box(box)
    d = len(lo0)
    if rtol < 0 or atol < 0:
        raise ValueError("rtol and atol must be >= 0")
    ev = _Evaluator(fun, index, negate, d)
    scale = [(b - a) if b > a else 1.0 for a, b in zip(lo0, hi0)]
    max_boxes = box_budget() if max_boxes is None else int(max_boxes)
    best = -INF  # incumbent: a proved lower bound of the sup
    arg: list[float] | None = None

    def offer(iv, x):
        nonlocal best, arg
        if iv is not None:
            v = fdn(iv[0])
            if v > best:
                best, arg = v, list(x)

    if seeds is not None:
        S = np.atleast_2d(np.asarray(seeds, dtype=float))
        if S.size and S.shape[1] != d:
            raise ValueError(f"seeds must have shape (k, {d}), got {S.shape}")
        for s in S:
            if np.all(np.isfinite(s)):
                p = np.clip(s, lo0, hi0)  # a seed just outside the box (rounding) still helps
                offer(ev.point([float(v) for v in p]), p)

    counter = 0
    heap: list = []
    dropped = -INF  # the largest upper bound of a box dropped for upper <= incumbent
    final = -INF  # the largest upper bound of a box too small to split

    def push(lo, hi):
        nonlocal counter, dropped
        c = centre(lo, hi)
        enc, fc, smear, updir = ev.box(lo, hi, c)
        counter += 1
        offer(fc, c)
        if updir is not None and any(updir):
            # Where the sign of the gradient is known, the best point is on that face (boundary maxima).
            p = _toward(lo, hi, c, updir)
            offer(ev.point(p), p)
        up = INF if enc is None else fup(enc[1])
        if up <= best:
            dropped = max(dropped, up)
        else:
            heapq.heappush(heap, (-up, counter, lo, hi, smear))

    push(lo0, hi0)
    proved = False
    while True:
        upper = max(-heap[0][0] if heap else -INF, dropped, final)
        if math.isfinite(upper) and best > -INF and upper - best <= rtol * abs(best) + atol:
            proved = True
            break
        if not heap or counter >= max_boxes:
            break
        neg_up, _, lo, hi, smear = heapq.heappop(heap)
        if -neg_up <= best:
            dropped = max(dropped, -neg_up)
            continue
        cut = _widest(lo, hi, scale, smear)
        if cut is None:
            final = max(final, -neg_up)
            continue
        k, m = cut
        push(lo, hi[:k] + [m] + hi[k + 1 :])
        push(lo[:k] + [m] + lo[k + 1 :], hi)
    _record(counter, max_boxes, proved, upper - best if best > -INF else INF)
    if not math.isfinite(upper):
        upper = INF
    argv = np.array(arg, dtype=float) if arg is not None else np.full(d, math.nan)
    return upper, best, argv, counter, proved


def sup_on_box(
    fun,
    box: np.ndarray,
    *,
    index: int = 0,
    rtol: float = 1e-3,
    atol: float = 0.0,
    max_boxes: int | None = None,
    seeds: np.ndarray | None = None,
) -> SupResult:
    """A rigorous upper bound of the supremum of one output of ``fun`` over a box (branch and bound).

    Parameters
    ----------
    fun : IntervalFunction or callable
        A compiled function (fast path: natural and mean-value enclosures) or any interval extension
        ``fun(list[arb]) -> list[arb]``.
    box : ndarray, shape (d, 2)
        One [lo, hi] row per argument.
    index : int
        Which output of ``fun`` to maximise.
    rtol, atol : float
        Stop once ``upper - lower <= rtol*|lower| + atol``.
    max_boxes : int, optional
        Budget of box evaluations (default: :func:`box_budget`).  Never a clock: the result is the same on any
        machine and load.
    seeds : ndarray, shape (k, d), optional
        Points evaluated first to start the incumbent (e.g. a grid argmax); clipped into the box.

    Returns
    -------
    SupResult
        ``upper`` is a rigorous bound whenever it is finite, even when ``proved`` is False (budget).

    Notes
    -----
    Boxes are kept in a priority queue keyed by their enclosure's upper end; the worst is bisected, the
    halves are enclosed and their centres evaluated (raising the incumbent), and boxes whose upper end
    is <= the incumbent are dropped.  A box with a non-finite enclosure has upper end ``inf`` and is
    split first.  For a compiled function the enclosure is the natural one intersected with the
    mean-value form, the split dimension is the one along which f may change most (|df/dx_k| times the
    width; the widest relative to the original box without a gradient), and where the sign of a partial
    derivative is known the point on the matching face is evaluated too (boundary maxima).
    """
    upper, lower, arg, boxes, proved = _branch_and_bound(fun, box, index, False, rtol, atol, max_boxes, seeds)
    return SupResult(upper=upper, lower=lower, argmax=arg, boxes=boxes, proved=proved)


def inf_on_box(
    fun,
    box: np.ndarray,
    *,
    index: int = 0,
    rtol: float = 1e-3,
    atol: float = 0.0,
    max_boxes: int | None = None,
    seeds: np.ndarray | None = None,
) -> InfResult:
    """A rigorous lower bound of the infimum of one output of ``fun`` over a box.

    The mirror of :func:`sup_on_box` (it maximises ``-f``).

    Parameters
    ----------
    fun, box, index, rtol, atol, max_boxes, seeds : as :func:`sup_on_box`
        ``index`` is the output to minimise; ``rtol``, ``atol`` stop on ``upper - lower``.

    Returns
    -------
    InfResult
        ``lower`` is rigorous whenever finite; ``upper`` is a value reached at ``argmin``.
    """
    upper, lower, arg, boxes, proved = _branch_and_bound(fun, box, index, True, rtol, atol, max_boxes, seeds)
    return InfResult(lower=-upper + 0.0, upper=-lower + 0.0, argmin=arg, boxes=boxes, proved=proved)  # (+0.0: no -0.0)


def prove_positive(
    fun,
    box: np.ndarray,
    *,
    index: int = 0,
    max_boxes: int | None = None,
) -> tuple[bool, float]:
    """Prove f > 0 on a whole box, or refute it at a point, by splitting the box.

    Parameters
    ----------
    fun : IntervalFunction or callable
        As for :func:`sup_on_box`.
    box : ndarray, shape (d, 2)
    index : int
        Which output of ``fun``.
    max_boxes : int, optional
        Budget, as for :func:`sup_on_box`.

    Returns
    -------
    (bool, float)
        ``(True, m)`` with ``0 < m <= inf_box f`` rigorous when proved (``m`` may round to 0.0 only if
        the true bound is below the smallest double); ``(False, v)`` with ``v >= f(x) `` and ``v <= 0``
        for a point x of the box once one is found (f is not positive); ``(False, b)`` on budget, ``b``
        the best rigorous lower bound of f over the box so far (``-inf`` if some enclosure stayed
        non-finite).
    """
    lo0, hi0 = check_box(box)
    d = len(lo0)
    ev = _Evaluator(fun, index, False, d)
    scale = [(b - a) if b > a else 1.0 for a, b in zip(lo0, hi0)]
    max_boxes = box_budget() if max_boxes is None else int(max_boxes)
    heap: list = []
    counter = 0
    proved_min = None  # smallest lower end among boxes proved positive (an exact arb)
    stuck_min = INF  # lower bounds of boxes too small to split that are not proved

    def visit(lo, hi):
        """Enclose a box; returns a refuting value, or None after queueing/recording the box."""
        nonlocal counter, proved_min
        c = centre(lo, hi)
        enc, fc, smear, updir = ev.box(lo, hi, c)
        counter += 1
        if fc is not None and fc[1] <= ZERO:
            return fup(fc[1])
        if enc is not None and enc[0] > ZERO:
            proved_min = enc[0] if proved_min is None else min(proved_min, enc[0])
            return None
        if updir is not None and any(updir):
            fp = ev.point(_toward(lo, hi, c, [-u for u in updir]))  # the face where f is lowest
            if fp is not None and fp[1] <= ZERO:
                return fup(fp[1])
        low = -INF if enc is None else fdn(enc[0])
        heapq.heappush(heap, (low, counter, lo, hi, smear))
        return None

    def refuted(v):
        _record(counter, max_boxes, True, 0.0)       # a point where f <= 0 settles the question
        return False, v

    v = visit(lo0, hi0)
    if v is not None:
        return refuted(v)
    while heap:
        if counter >= max_boxes:
            break
        low, _, lo, hi, smear = heapq.heappop(heap)
        cut = _widest(lo, hi, scale, smear)
        if cut is None:
            stuck_min = min(stuck_min, low)
            continue
        k, m = cut
        for sub in ((lo, hi[:k] + [m] + hi[k + 1 :]), (lo[:k] + [m] + lo[k + 1 :], hi)):
            v = visit(*sub)
            if v is not None:
                return refuted(v)
    bounds = [stuck_min] + ([heap[0][0]] if heap else [])
    if proved_min is not None:
        bounds.append(fdn(proved_min))
    if not heap and stuck_min == INF:
        _record(counter, max_boxes, True, 0.0)
        return True, fdn(proved_min)
    _record(counter, max_boxes, False, -min(bounds))    # how far below 0 the lower bound was left
    return False, min(bounds)


# --- matrices -------------------------------------------------------------------------------------------


def psd_lower_bound(S: np.ndarray) -> float:
    """A rigorous lower bound on the smallest eigenvalue of a symmetric float matrix.

    Parameters
    ----------
    S : ndarray, shape (n, n)
        Entries are taken as exact doubles; if S is not exactly symmetric, its symmetric part
        (S + S^T)/2 is used (formed exactly in arb).

    Returns
    -------
    float
        ``b`` with ``lambda_min((S + S^T)/2) >= b``; ``-inf`` if nothing could be proved.

    Raises
    ------
    ValueError
        If S is not a non-empty square matrix.
    NumericalError
        If S has non-finite entries.

    Notes
    -----
    With ``tau`` just below numpy's estimate of lambda_min, a float Cholesky factor L of S - tau I is
    computed and the residual R = S - tau I - L L^T is enclosed in arb.  As L L^T is positive
    semidefinite for any real L, Weyl's inequality gives lambda_min(S) >= tau - ||R||_2 >= tau - ||R||_F.
    If the Cholesky fails, tau is lowered (a few times).
    """
    S = np.asarray(S, dtype=float)
    if S.ndim != 2 or S.shape[0] != S.shape[1] or S.shape[0] == 0:
        raise ValueError(f"psd_lower_bound needs a non-empty square matrix, got shape {S.shape}")
    if not np.all(np.isfinite(S)):
        raise NumericalError("psd_lower_bound", "the matrix has non-finite entries", "a finite symmetric matrix")
    n = S.shape[0]
    if np.array_equal(S, S.T):
        A = S
        A_arb = arb_mat(S.tolist())
    else:
        A = 0.5 * (S + S.T)
        A_arb = (arb_mat(S.tolist()) + arb_mat(S.T.tolist())) * arb(0.5)
    amax = float(np.max(np.abs(A)))
    try:
        with np.errstate(all="ignore"):
            lam = float(np.linalg.eigvalsh(A)[0])
            norm = float(np.linalg.norm(A / amax)) * amax if amax > 0 else 0.0  # scaled: no overflow
    except np.linalg.LinAlgError:
        return -INF
    if not (math.isfinite(lam) and math.isfinite(norm)):
        return -INF
    # Shift below the estimate by a few times the Cholesky backward error, then more if it fails.
    base = 8.0 * (n + 1) * np.finfo(float).eps * max(norm, np.finfo(float).tiny)
    eye = np.eye(n)
    for k in range(8):
        tau = lam - base * 100.0**k
        if not math.isfinite(tau):
            break
        try:
            with np.errstate(all="ignore"):
                L = np.linalg.cholesky(A - tau * eye)
        except np.linalg.LinAlgError:
            continue
        if not np.all(np.isfinite(L)):
            continue
        La = arb_mat(L.tolist())
        R = A_arb - La * La.transpose()
        t = arb(tau)
        sq = arb(0)
        for i in range(n):
            for j in range(n):
                r = R[i, j] - t if i == j else R[i, j]
                m = r.abs_upper()
                sq += m * m
        if not sq.is_finite():
            continue
        return fdn(t - sq.sqrt().upper())
    return -INF


def prove_psd(S: np.ndarray, margin: float = 0.0) -> bool:
    """Whether lambda_min of the symmetric float matrix S is proved >= ``margin`` (see :func:`psd_lower_bound`).

    Parameters
    ----------
    S : ndarray (n, n)
        Symmetric.
    margin : float
        The least eigenvalue to prove.

    Returns
    -------
    bool
        True only when the rigorous lower bound of lambda_min(S) is >= margin.
    """
    return psd_lower_bound(S) >= margin


def lambda_max_upper(G) -> float:
    """A rigorous upper bound of the largest eigenvalue of a symmetric matrix known entrywise as arbs.

    Parameters
    ----------
    G : list of lists of arb, or arb_mat, shape (n, n)
        Enclosures of the entries of a real symmetric matrix (e.g. of A^T A computed in arb).

    Returns
    -------
    float
        ``max_i (g_ii + sum_{j != i} |g_ij|)`` over the upper ends of the balls (Gershgorin), rounded
        up; ``inf`` if an entry is not finite.
    """
    if isinstance(G, arb_mat):
        rows = [[G[i, j] for j in range(G.ncols())] for i in range(G.nrows())]
    else:
        rows = [[x if isinstance(x, arb) else arb(x) for x in row] for row in G]
    n = len(rows)
    if n == 0 or any(len(r) != n for r in rows):
        raise ValueError("lambda_max_upper needs a non-empty square matrix")
    if not all(g.is_finite() for row in rows for g in row):
        return INF
    best = -INF
    for i, row in enumerate(rows):
        s = row[i].upper()
        for j, g in enumerate(row):
            if j != i:
                s = s + g.abs_upper()
        best = max(best, fup(s))
    return best
