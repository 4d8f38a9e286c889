"""Proofs of the stages' claims: exact symbolic identities, ball arithmetic over sets, and matrix inequalities.

Every check a stage stores says how it was established (``Check.evidence``):

* ``proved``: the claim holds on the whole set it is about.  Three kinds of proof are used here:
  a sympy identity (a residual that simplifies to 0), a rigorous enclosure by arb ball arithmetic over the
  set (:mod:`ashc_cli.numerics.interval`; branch and bound for sups and infs, :mod:`ashc_cli.numerics.boxsearch`), and positive semidefiniteness of a
  matrix whose entries are enclosed in balls (an arb Cholesky factorisation);
* ``sampled``: the claim was checked on a finite set of points and could fail between them;
* ``simulated``: the claim was observed along simulated runs.

A stage tries the proof first and keeps its sampled number when the proof is out of reach (an expression
ball arithmetic cannot enclose, a budget exhausted, too many states); the proved number of a sup is an
upper bound, a little above the sampled maximum, and the stage uses it.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
import sympy as sp
from flint import arb

from ashc_cli.numerics import boxsearch, interval
from ashc_cli.numerics._infsup import ball_of, fdn, fup
from ashc_cli.problem.model import SIMPLIFY_MAX_OPS, Model, is_sparse, nonzero_entries

__all__ = ["PROVED", "SAMPLED", "SIMULATED", "symbolic_zero", "affine_in", "BoxFunction", "compile_claims", "sup_on_box",
           "inf_on_box", "range_on_box", "norm_expr", "ball", "ball_box", "upper", "lower", "psd_lower_bound_balls",
           "lambda_min_lower", "matrix_balls", "quadratic_form_terms", "norm_sqrt_M", "exact", "exact_number", "jump_inside", "refuse_jumps", "sparse_psd_lower_bound"]

PROVED, SAMPLED, SIMULATED = "proved", "sampled", "simulated"

#: Above this many states the proofs that build n x n ball matrices or n-vector enclosures are skipped
#: ("sampled"): an arb Cholesky in Python grows like n^3.
MAX_PROOF_STATES = 64

#: The work budget of the symbolic identities: operations (``count_ops``) simplified, summed over the expressions of
#: one claim.  A claim over more is left "sampled"; work, not seconds, so the verdict is the same on any machine.
SIMPLIFY_TOTAL_OPS = 10 * SIMPLIFY_MAX_OPS


def symbolic_zero(exprs: Sequence[sp.Expr], max_ops: int = SIMPLIFY_MAX_OPS, total_ops: int = SIMPLIFY_TOTAL_OPS) -> bool:
    """True when sympy proves every expression identically zero (skipped for expressions above ``max_ops``).

    sympy's ``simplify`` never claims 0 for a non-zero expression; it may fail to find a true 0, which only
    means the claim is left "sampled".

    Parameters
    ----------
    exprs : sequence of sympy Expr
        The residuals (anything ``sympify`` takes).
    max_ops : int
        An expression with more operations (``count_ops``) is not simplified: the answer is then False.
    total_ops : int
        Once the expressions simplified so far sum to more operations, no further ``simplify`` is started (the
        answer is then False): a budget of work, so the answer does not depend on the machine's load.

    Returns
    -------
    bool
        True when every expression is proved 0; False when one is not, or was skipped.
    """
    spent = 0
    for e in exprs:
        e = sp.sympify(e)
        if e == 0:
            continue
        ops = sp.count_ops(e)
        spent += ops
        if ops > max_ops or spent > total_ops:
            return False
        if sp.simplify(sp.together(e)) != 0:
            return False
    return True


def affine_in(exprs: sp.MatrixBase, symbols: Sequence[sp.Symbol]) -> bool:
    """True when every entry is affine in ``symbols`` (its derivatives by them are free of them).

    Parameters
    ----------
    exprs : sympy Matrix
        The entries to test (any iterable of expressions).
    symbols : sequence of Symbol
        The variables (e.g. ``model.u``).

    Returns
    -------
    bool
    """
    syms = set(symbols)
    for e in (nonzero_entries(exprs).values() if is_sparse(exprs) else exprs):
        for s in symbols:
            if s in e.free_symbols and sp.diff(e, s).free_symbols & syms:
                return False
    return True


def ball(lo: float, hi: float) -> arb:
    """An arb ball containing the float interval [lo, hi].

    Parameters
    ----------
    lo, hi : float
        The ends (taken as exact doubles).

    Returns
    -------
    arb
    """
    return ball_of(lo, hi)


def ball_box(box: np.ndarray) -> list[arb]:
    """One ball per row [lo, hi] of a box.

    Parameters
    ----------
    box : ndarray (d, 2)
        One [lo, hi] row per coordinate.

    Returns
    -------
    list of arb
        d balls, each containing its row's interval (:func:`ball`).
    """
    return [ball(float(lo), float(hi)) for lo, hi in np.asarray(box, dtype=float)]


def upper(x: arb) -> float:
    """A float >= every point of the ball (inf if it is not finite).

    Parameters
    ----------
    x : arb

    Returns
    -------
    float
        The ball's upper end, rounded up to a double.
    """
    return fup(x) if x.is_finite() else np.inf


def lower(x: arb) -> float:
    """A float <= every point of the ball (-inf if it is not finite).

    Parameters
    ----------
    x : arb

    Returns
    -------
    float
        The ball's lower end, rounded down to a double.
    """
    return fdn(x) if x.is_finite() else -np.inf


class BoxFunction:
    """Sympy matrices compiled for ball arithmetic, evaluated together on a box of their arguments.

    Parameters
    ----------
    model : Model
        Supplies the parameter values.
    terms : dict of str to sympy Matrix
        The matrices to enclose.
    args : sequence of Symbol
        Their arguments, in the order of the box's rows.
    """

    def __init__(self, model: Model, terms: dict[str, sp.MatrixBase], args: Sequence[sp.Symbol]):
        self.names = list(terms)
        self.shapes = [sp.Matrix(t).shape for t in terms.values()]
        flat = [e for t in terms.values() for e in sp.Matrix(t)]
        self._fun = interval.compile_interval(flat, list(args), model.values)

    def __call__(self, balls: Sequence[arb]) -> dict[str, list[list[arb]]]:
        """Each term as a nested list of balls (rows of columns) enclosing its values on the box."""
        flat = self._fun(list(balls))
        out, k = {}, 0
        for name, (r, c) in zip(self.names, self.shapes):
            out[name] = [[flat[k + i * c + j] for j in range(c)] for i in range(r)]
            k += r * c
        return out


def compile_claims(model: Model, exprs: Sequence[sp.Expr], args: Sequence[sp.Symbol]):
    """Scalar expressions compiled for the branch-and-bound searches (with derivatives: tight enclosures).

    Raises ``interval.UnsupportedExpression`` for an expression ball arithmetic cannot enclose.

    Parameters
    ----------
    model : Model
        Supplies the parameter values (``model.values``, each taken as its exact double).
    exprs : sequence of sympy Expr
        The scalar claims.
    args : sequence of Symbol
        The arguments, in the order of the box's rows.

    Returns
    -------
    IntervalFunction
        ``fun(balls) -> list[arb]``: one ball per expression enclosing its range over the balls' box
        (:func:`interval.compile_interval`).
    """
    return interval.compile_interval([sp.sympify(e) for e in exprs], list(args), model.values)


def sup_on_box(fun, box: np.ndarray, index: int = 0, seeds: np.ndarray | None = None, rtol: float = 1e-6,
               max_boxes: int | None = None, atol: float = 0.0) -> tuple[float, bool, np.ndarray]:
    """A proved upper bound of sup over the box of output ``index`` of fun, whether it is finite, and where the
    largest value found lies (:func:`boxsearch.sup_on_box`).

    Parameters
    ----------
    fun : IntervalFunction or callable
        From :func:`compile_claims`, or any interval extension ``fun(list[arb]) -> list[arb]``.
    box : ndarray (d, 2)
        One [lo, hi] row per argument of fun.
    index : int
        Which output of fun.
    seeds : ndarray (k, d), optional
        Points evaluated first (e.g. a grid's argmax); clipped into the box.
    rtol : float
        The search stops once the bound is within rtol (relative) of the largest value found.
    max_boxes : int, optional
        Boxes of branch and bound (default: the stage's ``proofs.max_boxes``, :func:`boxsearch.box_budget`); when
        spent, the bound reached so far is returned (still rigorous) and the stage's proof work records it.
    atol : float
        ... or within atol (absolute): needed where the sup is 0, which no relative tolerance reaches.

    Returns
    -------
    upper : float
        The proved bound (inf when the enclosure stayed non-finite).
    finite : bool
        Whether ``upper`` is finite.
    argmax : ndarray (d,)
        Where the largest value found lies (nan if none).
    """
    res = boxsearch.sup_on_box(fun, np.asarray(box, dtype=float), index=index, rtol=rtol, atol=atol, max_boxes=max_boxes, seeds=seeds)
    return float(res.upper), bool(np.isfinite(res.upper)), np.asarray(res.argmax, dtype=float)


def inf_on_box(fun, box: np.ndarray, index: int = 0, seeds: np.ndarray | None = None, rtol: float = 1e-6,
               max_boxes: int | None = None, atol: float = 0.0) -> tuple[float, bool]:
    """A proved lower bound of inf over the box of output ``index`` of fun and whether it is finite.

    Parameters
    ----------
    fun, box, index, seeds, rtol, max_boxes, atol
        As for :func:`sup_on_box`.

    Returns
    -------
    lower : float
        The proved bound (-inf when the enclosure stayed non-finite).
    finite : bool
        Whether ``lower`` is finite.
    """
    res = boxsearch.inf_on_box(fun, np.asarray(box, dtype=float), index=index, rtol=rtol, atol=atol, max_boxes=max_boxes, seeds=seeds)
    return float(res.lower), bool(np.isfinite(res.lower))


def range_on_box(fun, box: np.ndarray, index: int = 0, rtol: float = 1e-6) -> tuple[float, float, bool]:
    """Proved bounds lo <= f <= hi of output ``index`` over the box, and whether both are finite.

    Parameters
    ----------
    fun, box, index, rtol
        As for :func:`sup_on_box` (each end gets the stage's box budget).

    Returns
    -------
    lo, hi : float
    finite : bool
    """
    lo, ok_lo = inf_on_box(fun, box, index, rtol=rtol)
    hi, ok_hi, _ = sup_on_box(fun, box, index, rtol=rtol)
    return lo, hi, ok_lo and ok_hi


def norm_expr(M: np.ndarray, w: sp.MatrixBase) -> sp.Expr:
    """||sqrt(M) w||_2 as a sympy expression, M's entries exact doubles: sqrt(w^T M w) for a column w, and
    sqrt(lambda_max(G)) with the closed form of the largest eigenvalue of the 2 x 2 Gram matrix G = w^T M w
    for two columns.

    Parameters
    ----------
    M : ndarray (n, n)
        Symmetric; only its non-zero entries enter, each as a sympy Float.
    w : sympy Matrix (n, k), k = 1 or 2
        The columns (ValueError for more).

    Returns
    -------
    sympy Expr
    """
    M = np.asarray(M, dtype=float)
    nz = [(i, j) for i, j in zip(*np.nonzero(M))]

    def gram(a: int, b: int) -> sp.Expr:
        # sum_i w_ia (M w_b)_i over the non-zero entries, built unevaluated: sympy would otherwise distribute
        # every Float over the polynomials (seconds at n = 32); the interval compiler shares the w_i.
        rows = {}
        for i, j in nz:
            rows.setdefault(i, []).append(sp.Mul(sp.Float(float(M[i, j])), w[j, b], evaluate=False))
        return sp.Add(*[sp.Mul(w[i, a], sp.Add(*terms, evaluate=False), evaluate=False) for i, terms in rows.items()], evaluate=False)

    k = w.shape[1]
    G = sp.Matrix(k, k, lambda a, b: gram(a, b))
    if G.shape == (1, 1):
        return sp.sqrt(G[0, 0])
    if G.shape != (2, 2):
        raise ValueError("norm_expr takes one or two columns")
    half_sum, half_diff = (G[0, 0] + G[1, 1]) / 2, (G[0, 0] - G[1, 1]) / 2
    return sp.sqrt(half_sum + sp.sqrt(half_diff**2 + G[0, 1] ** 2))


def psd_lower_bound_balls(S: Sequence[Sequence[arb]]) -> float:
    """A proved lower bound of lambda_min of every symmetric matrix inside the ball matrix S.

    lambda_min(S) >= lambda_min(mid S) - ||S - mid S||_2 (Weyl), and ||E||_2 <= ||E||_F <= n max |E_ij|;
    lambda_min(mid S) is bounded below by an arb Cholesky factorisation (:func:`boxsearch.psd_lower_bound`).

    Parameters
    ----------
    S : list of lists of arb (n, n)
        The ball matrix (rows of entries).

    Returns
    -------
    float
        The proved bound; -inf if an entry is not finite or the Cholesky proves nothing.
    """
    n = len(S)
    if any(not S[i][j].is_finite() for i in range(n) for j in range(n)):
        return -np.inf
    mid = np.array([[float(S[i][j].mid()) for j in range(n)] for i in range(n)])
    mid = 0.5 * (mid + mid.T)
    # Distance of every ball entry from the (symmetrised) midpoint, rounded up.
    rad = max(upper(abs(S[i][j] - arb(mid[i, j]))) for i in range(n) for j in range(n))
    return float(boxsearch.psd_lower_bound(mid)) - np.nextafter(n * rad, np.inf)


def lambda_min_lower(S: np.ndarray) -> float:
    """A proved lower bound of lambda_min of a symmetric float matrix (entries exact doubles).

    Parameters
    ----------
    S : ndarray (n, n)
        Its symmetric part (S + S^T) / 2 is used if S is not exactly symmetric.

    Returns
    -------
    float
        The bound (-inf if nothing could be proved).
    """
    return float(boxsearch.psd_lower_bound(np.asarray(S, dtype=float)))


def matrix_balls(A: np.ndarray) -> list[list[arb]]:
    """A float matrix as exact balls.

    Parameters
    ----------
    A : ndarray (r, c)

    Returns
    -------
    list of lists of arb (r, c)
        One radius-0 ball per entry, rows of columns.
    """
    return [[arb(float(a)) for a in row] for row in np.asarray(A, dtype=float)]


def quadratic_form_terms(M: np.ndarray, A: Sequence[Sequence[arb]]) -> list[list[arb]]:
    """A^T M A in ball arithmetic (A a ball matrix n x k, M a float matrix): the Gram matrix of sqrt(M) A.

    Parameters
    ----------
    M : ndarray (n, n)
        Entries taken as exact doubles.
    A : list of lists of arb (n, k)

    Returns
    -------
    list of lists of arb (k, k)
    """
    n, k = len(A), len(A[0])
    Mb = matrix_balls(M)
    MA = [[sum((Mb[i][l] * A[l][j] for l in range(n)), arb(0)) for j in range(k)] for i in range(n)]
    return [[sum((A[l][i] * MA[l][j] for l in range(n)), arb(0)) for j in range(k)] for i in range(k)]


def norm_sqrt_M(M: np.ndarray, A: Sequence[Sequence[arb]]) -> arb:
    """||sqrt(M) A||_2 enclosed from above: exact for one column; for several, sqrt of an upper bound of the largest
    eigenvalue of the Gram matrix A^T M A, the smaller of Gershgorin's and Weyl's around the midpoint's (an arb
    Cholesky of lambda I - mid; tight when the balls are narrow, Gershgorin when they are wide).

    Parameters
    ----------
    M : ndarray (n, n)
        Symmetric positive semidefinite, entries taken as exact doubles.
    A : list of lists of arb (n, k)
        The ball matrix (e.g. dp/dxi delta enclosed over a box).

    Returns
    -------
    arb
        For one column, a ball containing the norm (non-finite if the Gram entry is); for several, the upper
        bound as an exact ball, or a nan ball when no finite bound was found.
    """
    G = quadratic_form_terms(M, A)
    if len(G) == 1:
        g = G[0][0]
        # g >= 0 mathematically; a ball reaching below 0 is clipped to [0, upper] before the root.
        if not g.is_finite():
            return g
        return g.sqrt() if g.lower() >= 0 else ball(0.0, upper(g)).nonnegative_part().sqrt()
    top = float(boxsearch.lambda_max_upper(G))
    if np.isfinite(top):
        weyl = -psd_lower_bound_balls([[-g for g in row] for row in G])
        top = min(top, weyl) if np.isfinite(weyl) else top
    return arb(max(top, 0.0)).sqrt() if np.isfinite(top) else arb("nan")


# --- exact rational arithmetic ------------------------------------------------------------------------------


def exact_number(x: float) -> sp.Rational:
    """The number a double stands for, as an exact rational: the shortest decimal that reads back as the same double
    (Python's repr), so 0.1 is 1/10, as the spec wrote it; an integer-valued double is that integer.

    Parameters
    ----------
    x : float
        Finite (ValueError otherwise).

    Returns
    -------
    sympy Rational
    """
    x = float(x)
    if not np.isfinite(x):
        raise ValueError(f"exact_number: {x} is not finite")
    return sp.Rational(repr(x))


def exact(model: Model, expr) -> sp.Matrix:
    """An expression with the parameters and every Float replaced by exact rationals (:func:`exact_number`).

    Exact decisions (an identity such as the PDE residual simplifying to 0, a matrix rank, whether the end of one
    set lies inside another) read the spec's numbers as the decimals written, so that l(V) = U at an end or
    kappa(V) = Y at a vertex is decided as equal rather than by the rounding of 0.3 - 0.1 in doubles.  Ball
    arithmetic (:mod:`ashc_cli.numerics.interval`) takes each number as its double; the two readings differ by the last
    bit of the parameters, far below any margin a certificate relies on.

    Parameters
    ----------
    model : Model
        Supplies the parameter values (``model.values``).
    expr : sympy Matrix or list of expressions
        What to convert (a list becomes a column); a bare scalar is not accepted by ``sp.Matrix``.

    Returns
    -------
    sympy Matrix
    """
    e = sp.Matrix(sp.sympify(expr)) if not isinstance(expr, sp.MatrixBase) else sp.Matrix(expr)
    e = e.xreplace({k: exact_number(v) for k, v in model.values.items()})
    return e.xreplace({f: exact_number(float(f)) for f in e.atoms(sp.Float)})


def jump_inside(model: Model, fun: sp.Expr, args: Sequence[sp.Symbol], box: np.ndarray) -> tuple[bool, str]:
    """Whether a discontinuous function (sign(z), square(z), step(z)) can jump inside the box: its argument's
    enclosure over the box reaches its jump points (0 for sign and step; the zeros of sin for square).

    Returns (True, where) when it can, or when ball arithmetic cannot tell; (False, "") when z keeps off them.

    Parameters
    ----------
    model : Model
        Supplies the parameter values.
    fun : sympy Expr
        One application sign(z), square(z), step(z) or Heaviside(z), as :func:`~ashc_cli.problem.model.jumps` finds them.
    args : sequence of Symbol
        The symbols z may depend on, in the order of the box's rows.
    box : ndarray (d, 2)
        The set, one [lo, hi] row per symbol of ``args``.

    Returns
    -------
    inside : bool
    where : str
        The jump and the range of z on the box (or why it cannot be enclosed); "" when it cannot jump.
    """
    from ashc_cli.problem.expr import square

    z = fun.args[0]
    if isinstance(fun, square):
        z = sp.sin(z)
    try:
        lo, hi, ok = range_on_box(compile_claims(model, [z], list(args)), np.asarray(box, dtype=float))
    except interval.UnsupportedExpression:
        return True, f"{fun}: its argument cannot be enclosed"
    if not ok or lo <= 0 <= hi:
        return True, f"{fun} jumps where {z} = 0, and {z} ranges over [{lo:.6g}, {hi:.6g}] on the box"
    return False, ""


def refuse_jumps(model: Model, fields: Sequence[tuple[str, sp.Expr]], args: Sequence[sp.Symbol], box: np.ndarray,
                 what: str, expected: str, check: str) -> None:
    """Raise a DesignError naming the field and the function when a jump of sign, square or step of the states
    lies inside the box (:func:`jump_inside`); ``what`` says what fails there (it follows the jump's description).

    Parameters
    ----------
    model : Model
        Supplies the parameter values; only jumps whose argument depends on its states ``model.x`` count.
    fields : sequence of (str, sympy Expr)
        Each spec field (``concrete.f_bar[0]``) with its expression.
    args : sequence of Symbol
        The symbols of the box's rows.
    box : ndarray (d, 2)
        The set the jump must keep off.
    what : str
        What fails there (the DesignError's message, after the jump's description).
    expected : str
        The start of the DesignError's expected text (a concrete.state_box on one side of the jump is offered after it).
    check : str
        The check the DesignError names (e.g. ``lmi_margin``).
    """
    from ashc_cli.errors import DesignError
    from ashc_cli.problem.model import jumps

    for field, e in fields:
        for fun in jumps([e], model.x):
            inside, where = jump_inside(model, fun, args, box)
            if inside:
                raise DesignError(field, f"{where}: {what}", f"{expected} (e.g. tanh(k*z) for sign(z)), or a concrete.state_box on one side of the jump",
                                  check=check)


#: The banded LDL^T proof is attempted up to this many arb operations (n times the bandwidth squared).
BANDED_PROOF_OPS = 5e7


def sparse_psd_lower_bound(S: dict, n: int) -> float:
    """A proved lower bound of lambda_min of a symmetric matrix given as {(i, j): arb} (both triangles), or -inf.

    Up to :data:`MAX_PROOF_STATES` states the dense arb path (:func:`psd_lower_bound_balls`); above it, with tau half of
    a float estimate of lambda_min, the float banded Cholesky factor of S - tau I and its residual bounded in ball
    arithmetic along the band (:func:`_banded_cholesky_bound`; n w^2 operations for bandwidth w).

    Parameters
    ----------
    S : dict of (int, int) to arb
        The entries of the n x n matrix, both triangles; a missing entry is 0.
    n : int
        The size of the matrix.

    Returns
    -------
    float
        The proved bound; -inf when an entry is not finite, the band is too wide (:data:`BANDED_PROOF_OPS`), the
        estimate of lambda_min is not positive, or the factorisation fails.
    """
    if n <= MAX_PROOF_STATES:
        dense = [[S.get((i, j), arb(0)) for j in range(n)] for i in range(n)]
        return psd_lower_bound_balls(dense)
    import scipy.sparse as sps
    import scipy.sparse.linalg as spla

    keys = list(S)
    if any(not S[k].is_finite() for k in keys):
        return -np.inf
    width = max((abs(i - j) for i, j in keys), default=0)
    if n * max(1, width) ** 2 > BANDED_PROOF_OPS:
        return -np.inf
    mid = sps.csr_matrix(([float(S[k].mid()) for k in keys], ([k[0] for k in keys], [k[1] for k in keys])), shape=(n, n))
    mid = 0.5 * (mid + mid.T)
    try:
        # shift-invert about 0: the eigenvalue nearest 0 to full relative accuracy, however small (a long ladder's
        # is 1e-12 of its largest); when S is positive definite it is lambda_min
        estimate = float(spla.eigsh(mid.tocsc(), k=1, sigma=0.0, which="LM", return_eigenvectors=False, tol=1e-12, maxiter=20 * n)[0])
    except (spla.ArpackNoConvergence, RuntimeError, ValueError):
        try:
            estimate = float(spla.eigsh(mid.tocsc(), k=1, which="SA", return_eigenvectors=False, tol=1e-12, maxiter=20 * n)[0])
        except spla.ArpackNoConvergence:
            return -np.inf
    if not estimate > 0:
        return -np.inf
    return _banded_cholesky_bound(S, n, width, mid, 0.5 * estimate)


def _banded_cholesky_bound(S: dict, n: int, width: int, mid, shift: float) -> float:
    """shift - ||R||_inf, R = S - shift I - L L^T in ball arithmetic with L the float banded Cholesky factor of
    mid(S) - shift I (L L^T is positive semidefinite for any real L, so lambda_min(S) >= shift - ||R||_2 >= shift -
    ||R||_inf); -inf if the float factorisation fails.  The factor is fixed floats: no interval dependency grows
    along the factorisation, as it would in an LDL^T of balls."""
    import scipy.linalg as sla

    w = max(1, width)
    band = np.zeros((w + 1, n))                       # upper form: band[w + i - j, j] = A[i, j] for i <= j
    dense_mid = mid.tocoo()
    for i, j, v in zip(dense_mid.row, dense_mid.col, dense_mid.data):
        if i <= j and j - i <= w:
            band[w + i - j, j] = v
    band[w] -= shift
    try:
        U = sla.cholesky_banded(band, lower=False)     # A = U^T U, U upper with w super-diagonals
    except np.linalg.LinAlgError:
        return -np.inf
    # U[i, j] (i <= j <= i + w) is U_band[w + i - j, j]
    def u(i: int, j: int) -> float:
        return float(U[w + i - j, j]) if 0 <= j - i <= w else 0.0

    row_sums = [arb(0)] * n
    for i in range(n):
        for j in range(i, min(n, i + w + 1)):
            # (U^T U)_ij = sum_k U_ki U_kj over k <= min(i, j)
            acc = S.get((i, j), arb(0)) - (arb(shift) if i == j else arb(0))
            for k in range(max(0, j - w), i + 1):
                acc -= arb(u(k, i)) * arb(u(k, j))
            r = abs(acc)
            row_sums[i] += r
            if j != i:
                row_sums[j] += r
    norm = max(upper(r) for r in row_sums)
    return float(lower(arb(shift) - arb(norm)))
