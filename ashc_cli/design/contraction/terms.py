"""The Jacobian df/dx over concrete.state_box x U, for f not affine in x: the matrices the LMI is imposed on.

For f not affine in x, V(x, z) = (x - z)^T M (x - z) decays at rate lambda along any pair of solutions that stay in
the (convex) state box if J^T M + M J <= -lambda M for every J = df/dx(s, u) with s in the box (the mean-value form
f(x, u) - f(z, u) = int_0^1 J(z + s (x - z), u) ds (x - z)).
"""

from __future__ import annotations

import itertools
from dataclasses import dataclass

import numpy as np
import sympy as sp

from ashc_cli.numerics import proofs
from ashc_cli.errors import DesignError, SpecError
from ashc_cli.problem.grids import domain_grid, maximise_on_box
from ashc_cli.problem.model import Model, nonzero_entries, sparse_jacobian


#: At most this many Jacobian entries may vary over the state box (the polytope has 2^k vertices; more go to the
#: norm-bound test, whose cost grows with the entries).
MAX_VARYING_ENTRIES = 6


RANGE_SAMPLES = 40000


# Each end of one Jacobian entry's range is enclosed with the stage's box budget (proofs.max_boxes; when spent, the
# range is only sampled, and the LMI row says so).


#: Relative width at which that branch and bound stops (the enclosure is rigorous at any width; a tighter one
#: only makes the LMI less conservative).
ENCLOSURE_RTOL = 1e-6


def refuse_jumps(model: Model) -> None:
    """Refuse an f with a jump (sign, square, step of a state) inside state_box x U: the Jacobian LMI's mean-value
    argument needs f Lipschitz there.  (abs, min and max are Lipschitz and handled by their generalised derivatives.)

    Parameters
    ----------
    model : Model
        Its f_bar and g (or f) are checked over state_box x U (``concrete.state_box`` must be given).

    Raises
    ------
    DesignError
        Naming the field, the function and where its argument crosses the jump.
    """
    if model.affine:
        fields = [(f"concrete.f_bar[{i}]", e) for i, e in enumerate(model.f_bar)]
        fields += [(f"concrete.g[{i}][{j}]", e) for (i, j), e in model.g.todok().items() if e != 0]
    else:
        fields = [(f"concrete.f[{i}]", e) for i, e in enumerate(model.f)]
    proofs.refuse_jumps(model, fields, list(model.x) + list(model.u), np.r_[model.state_box, model.U],
                        "f is not Lipschitz on state_box x U, so no Jacobian LMI (eq. (28)) can certify it",
                        "a smooth approximation of the jump", check="lmi_margin")


def jacobian_polytope(model: Model, J: sp.Matrix | None = None) -> tuple[sp.Matrix, list[np.ndarray], np.ndarray, dict]:
    """A polytope containing the Jacobian df/dx(x, u) for x in ``concrete.state_box`` and u in U.

    For f not affine in x, V(x, z) = (x - z)^T M (x - z) decays at rate lambda along any pair of solutions
    that stay in the (convex) state box if J^T M + M J <= -lambda M for every J = df/dx(s, u) with s in the
    box (the mean-value form f(x, u) - f(z, u) = int_0^1 J(z + s (x - z), u) ds (x - z)).  Each entry of J
    that varies is enclosed over box x U by ball arithmetic with branch and bound (:func:`proofs.range_on_box`:
    rigorous at any width, so a steep term such as tanh(50000 x) whose derivative peaks in a band 1e-4 wide is
    inside the range), and the LMI is imposed at the 2^k vertices of the box of entry ranges, which contains J.
    Where ball arithmetic cannot enclose an entry (or the enclosure is not finite), its range comes from a
    grid refined by bounded local searches, widened by 1e-9 relative: the LMI is then only *sampled*
    (``meta["ranges_proved"]`` is False) and ``ashc check`` says so.

    Parameters
    ----------
    model : Model
        Supplies f, state_box and U.
    J : sympy Matrix (n, n), optional
        df/dx(x, u) if already computed (default: :func:`sparse_jacobian` of ``model.f``).

    Returns
    -------
    J : sympy Matrix
        df/dx(x, u).
    A_list : list of ndarray
        The vertex matrices.
    ranges : ndarray, shape (k, 2)
        The range of each varying entry.
    meta : dict
        Which entries vary, how their ranges were found (``ranges_proved``), and the sampled ranges beside them.

    Raises
    ------
    SpecError
        Without ``concrete.state_box``.
    DesignError
        If more than ``MAX_VARYING_ENTRIES`` entries vary, or an entry is unbounded on the box.
    """
    if model.state_box is None:
        raise SpecError("concrete.state_box", "missing: f(x, u) is not affine in x, so the incremental LMI is imposed on the Jacobian over a box of states",
                        "one pair [lo, hi] per state (the region the design is certified on)")
    J = sparse_jacobian(model.f, model.x) if J is None else J
    args = list(model.x) + list(model.u)
    box = np.r_[model.state_box, model.U]
    varying = [(i, j) for (i, j), e in np.ndenumerate(np.array(J, dtype=object)) if e.free_symbols & set(args)]
    if len(varying) > MAX_VARYING_ENTRIES:
        raise DesignError("concrete", f"{len(varying)} Jacobian entries vary over the state box (at most {MAX_VARYING_ENTRIES}: the polytope has 2^k vertices)",
                          "fewer state-dependent terms, or f affine in x")
    pts = domain_grid(box, RANGE_SAMPLES)
    ranges, sampled, how = [], [], []
    for i, j in varying:
        name = f"df{i + 1}/d{model.x[j]}"
        fun = model.numeric([J[i, j]], args)
        vals = np.broadcast_to(fun(*pts)[0, 0], pts.shape[1])
        if not np.all(np.isfinite(vals)):
            bad = pts[:, int(np.argmax(~np.isfinite(vals)))]
            raise DesignError("concrete.state_box", f"{name} is not finite on the box (at {np.round(bad, 6).tolist()})", "a box on which f is C^1")
        hi, _ = maximise_on_box(pts, vals, lambda z, fun=fun: float(fun(*z)[0, 0]), box)
        neg_lo, _ = maximise_on_box(pts, -vals, lambda z, fun=fun: -float(fun(*z)[0, 0]), box)
        lo = -neg_lo
        sampled.append((lo, hi))
        enclosed = enclose_entry(model, J[i, j], args, box)
        if enclosed is not None:
            ranges.append(enclosed)
            how.append("enclosed")
        else:
            pad = 1e-9 * max(1.0, abs(lo), abs(hi))
            ranges.append((lo - pad, hi + pad))
            how.append("sampled")
    # The constant entries; the varying ones are set at each corner (never evaluated at x = 0, where 1/sqrt(x) of a
    # tank's outflow is not finite though the box excludes 0).
    J0 = np.zeros(J.shape)
    for (i, j), e in np.ndenumerate(np.array(J, dtype=object)):
        if (i, j) not in varying and e != 0:
            J0[i, j] = float(model.substitute(e))
    A_list = []
    for corner in itertools.product(*ranges):
        A = J0.copy()
        for (i, j), value in zip(varying, corner):
            A[i, j] = value
        A_list.append(A)
    proved = all(h == "enclosed" for h in how)
    meta = {"jacobian_entries": [f"df{i + 1}/d{model.x[j]}" for i, j in varying],
            "state_box": model.state_box.tolist(), "ranges_proved": proved,
            "range_method": ("ball-arithmetic enclosure over box x U by branch and bound (rigorous)" if proved else
                             "enclosure where ball arithmetic reaches, else a grid of box x U refined by L-BFGS-B and widened 1e-9 (sampled): "
                             + ", ".join(f"{n} {h}" for n, h in zip((f'df{i + 1}/d{model.x[j]}' for i, j in varying), how))),
            "ranges_sampled": [list(r) for r in sampled]}
    return J, A_list, np.array(ranges, dtype=float).reshape(-1, 2), meta


def enclose_term(fun, box: np.ndarray) -> tuple[float, float, bool]:
    """Proved bounds lo <= term <= hi over the box (branch and bound in ball arithmetic), and whether both are finite.

    The search stops within ``ENCLOSURE_RTOL`` of the term's size on the box (its largest |value| at the corners and
    the centre) as well as relatively: a term whose inf or sup is 0 (x2^2, tanh(x1)^2 on a box around 0) never
    closes a relative gap, and spent the whole box budget on a gap of 5e-324 (23 searches, 30 s of the 2-state
    saturating spring's stabilise stage).  Any tolerance gives a proved enclosure; this one is as tight as the
    relative one wherever the term is away from 0.

    Parameters
    ----------
    fun : IntervalFunction
        The term (:func:`proofs.compile_claims`), one output.
    box : ndarray (d, 2)
        The box of its arguments.

    Returns
    -------
    (lo, hi, finite) : (float, float, bool)
    """
    corners = list(itertools.product(*box)) if box.shape[0] <= 6 else []
    values = [fun([proofs.arb(float(v)) for v in point])[0] for point in [*corners, box.mean(axis=1)]]
    size = max((abs(float(v.mid())) for v in values if v.is_finite()), default=0.0)
    atol = ENCLOSURE_RTOL * size
    lo, ok_lo = proofs.inf_on_box(fun, box, rtol=ENCLOSURE_RTOL, atol=atol)
    hi, ok_hi, _ = proofs.sup_on_box(fun, box, rtol=ENCLOSURE_RTOL, atol=atol)
    return lo, hi, ok_lo and ok_hi


def enclose_entry(model: Model, entry: sp.Expr, args: list, box: np.ndarray) -> tuple[float, float] | None:
    """Proved bounds lo <= entry <= hi over the box (ball arithmetic, branch and bound), or None where ball
    arithmetic cannot enclose the entry or the enclosure is not finite.

    Parameters
    ----------
    model : Model
        Supplies the parameter values.
    entry : sympy Expr
        One entry of df/dx (or a term of it).
    args : list of Symbol
        The variables of the box's rows (the states, then the inputs).
    box : ndarray (len(args), 2)
        The box.

    Returns
    -------
    (float, float) or None
    """
    # Only the coordinates the entry depends on (a network's term reads two nodes of a thousand).
    free = entry.free_symbols
    used = [k for k, a in enumerate(args) if a in free]
    if not used:
        value = proofs.compile_claims(model, [entry], [])([])[0]
        return (proofs.lower(value), proofs.upper(value)) if value.is_finite() else None
    try:
        fun = proofs.compile_claims(model, [entry], [args[k] for k in used])
    except proofs.interval.UnsupportedExpression:
        return None
    lo, hi, ok = enclose_term(fun, np.asarray(box, dtype=float)[used])
    return (lo, hi) if ok else None


def jacobian_samples(model: Model, J: sp.Matrix, count: int | None = None, seed: int = 2,
                     points: np.ndarray | None = None) -> tuple[list[np.ndarray], np.ndarray]:
    """df/dx at random points of state_box x U (the numpy re-check of the Jacobian LMI), and the points (rows of (x, u)).

    2000 points up to 64 states, fewer above (each is a dense n x n matrix and an eigenvalue problem).

    Parameters
    ----------
    model : Model
        Supplies the parameter values, state_box and U.
    J : sympy Matrix (n, n)
        df/dx(x, u).
    count : int, optional
        The number of points (default 2000 up to 64 states, max(4, 2000 (64 / n)^2) above).
    seed : int
        Seed of numpy's ``default_rng``.
    points : ndarray (k, n + m), optional
        Points of (x, u) taken before the random ones (where a plant is singular: a speed of 0, the centre).

    Returns
    -------
    samples : list of ndarray (n, n)
        df/dx at each point.
    points : ndarray (count, n + m)
        The points, rows of (x, u).
    """
    if count is None:
        count = 2000 if model.n <= 64 else max(4, int(2000 * (64 / model.n) ** 2))
    rng = np.random.default_rng(seed)
    box = np.r_[model.state_box, model.U]
    pts = rng.uniform(box[:, 0:1], box[:, 1:2], size=(len(box), count))
    if points is not None:
        pts = np.c_[np.asarray(points, dtype=float).T, pts]
        count = pts.shape[1]
    # Only the non-zero entries are compiled (a network's Jacobian has 3 n of n^2).
    nonzero = [(i, j, e) for (i, j), e in J.todok().items() if e != 0]
    values = np.zeros(J.shape + (count,))
    if nonzero:
        fun = model.numeric([e for _, _, e in nonzero], list(model.x) + list(model.u))
        flat = np.broadcast_to(fun(*pts)[:, 0, :], (len(nonzero), count))
        for (i, j, _), row in zip(nonzero, flat):
            values[i, j] = row
    return list(np.moveaxis(values, -1, 0)), pts.T



# --- the Jacobian written over the plant's nonlinear terms ----------------------------------------------------

#: At most this many terms are enumerated as vertices (2^K corners of the box of term values; each refinement round of
#: `maximise` solves SDPs over up to 2048 of them: 9 terms took 157 s on a 3-pendulum ring, the norm-bound test 3 s).
MAX_VERTEX_TERMS = 6


@dataclass
class Terms:
    """df/dx(x, u) = A0 + sum_k theta_k(x, u) A_k over the distinct scalar nonlinear terms theta_k of the plant.

    Attributes
    ----------
    thetas : list of sympy expressions
        The terms theta_k(x, u) (parameters substituted), each appearing in one or more entries of df/dx.
    A0 : ndarray (n, n)
        The constant part.
    A : list of scipy.sparse.csr_matrix (n, n)
        The coefficient matrix of each term (sparse: a network's terms touch two nodes each).
    coefficients : list of dict
        A0 and the A_k as {(i, j): exact expression} (for the ball-arithmetic proof).
    ranges : ndarray (K, 2)
        Enclosures of each term over state_box x U.
    proved : bool
        Whether every range is a ball-arithmetic enclosure (else some come from samples).
    how : list of str
        For each term, "enclosed" or "sampled".
    """

    thetas: list
    A0: np.ndarray
    A: list
    coefficients: list
    ranges: np.ndarray
    proved: bool
    how: list

    def __len__(self) -> int:
        return len(self.thetas)

    def dense(self) -> list[np.ndarray]:
        """The coefficient matrices A_k as dense arrays."""
        return [A.toarray() for A in self.A]

    def vertex_matrices(self) -> list[np.ndarray]:
        """A0 + sum_k theta_k A_k at the 2^K corners of the box of term values (the corner order of itertools.product)."""
        dense = self.dense()
        return [self.A0 + sum((t * A for t, A in zip(corner, dense)), np.zeros_like(self.A0))
                for corner in itertools.product(*[tuple(r) for r in self.ranges])]

    def coefficient_matrices(self, n: int) -> list[sp.Matrix]:
        """A0 and the A_k as sympy matrices (n x n)."""
        return [sp.Matrix(n, n, lambda i, j, c=c: c.get((i, j), sp.S.Zero)) for c in self.coefficients]

    def describe(self) -> list[str]:
        """'theta_k = <expr> in [lo, hi] (enclosed)', one line a term."""
        return [f"{t} in [{lo:.6g}, {hi:.6g}] ({h})" for t, (lo, hi), h in zip(self.thetas, self.ranges, self.how)]


def _parts(e: sp.Expr) -> tuple:
    """The additive terms of e (expanded at the top level only; exp(a + b) and powers kept whole)."""
    return sp.Add.make_args(sp.expand(e, deep=False, power_exp=False, power_base=False, log=False, multinomial=False))


def _valued(model: Model, e: sp.Expr, args: list) -> sp.Expr:
    """e with the parameter values put in.  As doubles, sympy pulls a number out of an exponential (a diode's
    Is exp((x - 0.7) / Vt) becomes 1e-313 exp(1000 x), whose exp(1000 x) overflows on the box and whose
    coefficient is subnormal); where a coefficient comes out that way, the entry takes the spec's numbers as exact
    rationals instead, which keeps exp(1000 x - 700) whole for the enclosure."""
    floats = model.substitute(e)
    for part in _parts(floats):
        c, _ = part.as_independent(*args, as_Add=False)
        if c.free_symbols:
            continue
        value = abs(complex(c))
        if value != 0 and not (1e-250 < value < 1e250):
            return proofs.exact(model, [e])[0]
    return floats


def decompose(model: Model, J: sp.Matrix) -> Terms:
    """Write the Jacobian as A0 + sum_k theta_k A_k: each entry is split into its additive terms, each term into a
    constant coefficient and a factor that depends on (x, u); equal factors across the entries are one theta_k.

    An Arrhenius term exp(-E/T) that enters four entries of a reactor's Jacobian is then one or two terms, not four
    independent entries (a box of entries contains Jacobians no state produces); a diode exp(40 (x_k - x_k+1)) of a
    network is one rank-one term.

    Parameters
    ----------
    model : Model
        Supplies the parameter values (substituted first), state_box and U (the box the terms are enclosed on).
    J : sympy Matrix (n, n)
        df/dx(x, u).

    Returns
    -------
    Terms
    """
    import scipy.sparse as sps

    args = list(model.x) + list(model.u)
    argset = set(args)
    n = model.n
    const: dict = {}
    coeffs: dict = {}
    order: list = []
    for (i, j), e in sorted(J.todok().items()):
        if e == 0:
            continue
        if True:
            e = _valued(model, e, args)
            if not e.free_symbols & argset:
                const[(i, j)] = const.get((i, j), sp.S.Zero) + e
                continue
            for part in _parts(e):
                c, theta = part.as_independent(*args, as_Add=False)
                if theta == 1:
                    const[(i, j)] = const.get((i, j), sp.S.Zero) + c
                    continue
                if theta not in coeffs:
                    coeffs[theta] = {}
                    order.append(theta)
                coeffs[theta][(i, j)] = coeffs[theta].get((i, j), sp.S.Zero) + c
    A0 = np.zeros((n, n))
    for (i, j), c in const.items():
        A0[i, j] = float(c)
    As = []
    for theta in order:
        keys = list(coeffs[theta])
        As.append(sps.csr_matrix(([float(coeffs[theta][k]) for k in keys], ([k[0] for k in keys], [k[1] for k in keys])), shape=(n, n)))
    ranges, how = [], []
    box = np.r_[model.state_box, model.U]
    pts = None
    for theta in order:
        enclosed = enclose_entry(model, theta, args, box)
        if enclosed is not None:
            ranges.append(enclosed)
            how.append("enclosed")
            continue
        if pts is None:
            pts = domain_grid(box, RANGE_SAMPLES)
        fun = model.numeric([theta], args)
        vals = np.broadcast_to(fun(*pts)[0, 0], pts.shape[1])
        hi, _ = maximise_on_box(pts, vals, lambda z, fun=fun: float(fun(*z)[0, 0]), box)
        neg_lo, _ = maximise_on_box(pts, -vals, lambda z, fun=fun: -float(fun(*z)[0, 0]), box)
        pad = 1e-9 * max(1.0, abs(hi), abs(neg_lo))
        ranges.append((-neg_lo - pad, hi + pad))
        how.append("sampled")
    return Terms(thetas=order, A0=A0, A=As, coefficients=[const] + [coeffs[t] for t in order],
                 ranges=np.array(ranges, dtype=float).reshape(-1, 2), proved=all(h == "enclosed" for h in how), how=how)


# --- the polytope the LMI is imposed on ------------------------------------------------------------------------

@dataclass
class Polytope:
    """A finite set of matrices whose convex hull contains every df/dx the certificate must cover.

    Attributes
    ----------
    kind : str
        "affine in u" (A(u) at the vertices of U), "Jacobian entries" (the corners of the box of the varying entries)
        or "Jacobian terms" (the corners of the box of the values of the plant's nonlinear terms).
    matrices : list of ndarray
        The vertex matrices.
    labels : list of str
        What each vertex is (for messages): "u = [0.0]", "df2/dx1 = 1999.5" or "tanh(x1)**2 = 0.99866".
    proved : bool
        Whether the hull provably contains every df/dx (ball-arithmetic enclosures; affine: by construction).
    balls : callable
        () -> the vertex matrices as nested lists of arb balls (for the proof; may raise UnsupportedExpression).
    meta : dict
        What the artefact records about it.
    sparse_balls : callable or None
        () -> the vertex matrices as {(i, j): arb} of their nonzero entries (the proof above
        ``proofs.MAX_PROOF_STATES`` states, where n^2 balls would not do); None where not built.
    """

    kind: str
    matrices: list
    labels: list
    proved: bool
    balls: object
    meta: dict
    sparse_balls: object = None


def affine_polytope(model: Model, A_sym: sp.Matrix, U_vertices: np.ndarray) -> Polytope:
    """A(u) at the vertices of U (A affine in u): the LMI, affine in A, holds on U once it holds there.

    Parameters
    ----------
    model : Model
        Supplies u and the parameter values.
    A_sym : sympy Matrix (n, n)
        A(u) = df/dx, free of x.
    U_vertices : ndarray (2^m, m)
        The vertices of U (:func:`~ashc_cli.design.contraction.vertex.vertices`).

    Returns
    -------
    Polytope
        ``proved`` when A_sym is affine in u.
    """
    A_num = model.numeric(A_sym, list(model.u))

    def balls():
        fA = proofs.BoxFunction(model, {"A": A_sym}, list(model.u))
        return [fA([proofs.arb(float(c)) for c in vtx])["A"] for vtx in U_vertices]

    def sparse_balls():
        entries = nonzero_entries(A_sym)
        f = proofs.compile_claims(model, list(entries.values()), list(model.u))
        return [dict(zip(entries, f([proofs.arb(float(c)) for c in vtx]))) for vtx in U_vertices]

    return Polytope("affine in u", [np.asarray(A_num(*vtx), dtype=float) for vtx in U_vertices],
                    [f"u = {np.round(vtx, 6).tolist()}" for vtx in U_vertices], proofs.affine_in(A_sym, model.u), balls, {}, sparse_balls)


def entry_polytope(model: Model, J: sp.Matrix) -> Polytope:
    """The corners of the box of the varying entries of df/dx (:func:`jacobian_polytope`).

    Parameters
    ----------
    model : Model
        Supplies state_box, U and the parameter values.
    J : sympy Matrix (n, n)
        df/dx(x, u).

    Returns
    -------
    Polytope
        ``proved`` when every entry range is a ball-arithmetic enclosure; ``meta`` adds ``ranges``.
    """
    _, A_list, ranges, meta = jacobian_polytope(model, J)
    args = list(model.x) + list(model.u)
    varying = [(i, j) for (i, j), e in np.ndenumerate(np.array(J, dtype=object)) if e.free_symbols & set(args)]
    names = meta["jacobian_entries"]
    corners = list(itertools.product(*[tuple(r) for r in ranges]))

    def balls():
        fA = proofs.BoxFunction(model, {"A": J}, args)
        A_any = fA(proofs.ball_box(np.r_[model.state_box, model.U]))["A"]      # constant entries are thin balls
        out = []
        for corner in corners:
            A = [row[:] for row in A_any]
            for (i, j), value in zip(varying, corner):
                A[i][j] = proofs.arb(float(value))
            out.append(A)
        return out

    labels = [", ".join(f"{n} = {v:.6g}" for n, v in zip(names, c)) for c in corners]
    meta = {**meta, "ranges": ranges.tolist()}
    return Polytope("Jacobian entries", A_list, labels, bool(meta["ranges_proved"]), balls, meta)


def term_polytope(model: Model, terms: Terms) -> Polytope:
    """The corners of the box of the term values: A0 + sum_k theta_k A_k with each theta_k at an end of its range.

    Parameters
    ----------
    model : Model
        Supplies n and the parameter values.
    terms : Terms
        The decomposition (:func:`decompose`).

    Returns
    -------
    Polytope
        2^K matrices, ``proved`` when ``terms.proved``.
    """
    corners = list(itertools.product(*[tuple(r) for r in terms.ranges]))

    def balls():
        f = proofs.BoxFunction(model, {f"A{k}": A for k, A in enumerate(terms.coefficient_matrices(model.n))}, [])
        parts = f([])
        A0, As = parts["A0"], [parts[f"A{k + 1}"] for k in range(len(terms))]
        n = model.n
        out = []
        for corner in corners:
            out.append([[A0[i][j] + sum((proofs.arb(float(t)) * A[i][j] for t, A in zip(corner, As)), proofs.arb(0)) for j in range(n)]
                        for i in range(n)])
        return out

    labels = [", ".join(f"{t} = {v:.6g}" for t, v in zip(terms.thetas, c)) for c in corners]
    meta = {"jacobian_terms": [str(t) for t in terms.thetas], "term_ranges": terms.ranges.tolist(), "ranges_proved": terms.proved,
            "range_method": ("ball-arithmetic enclosure of each term over box x U by branch and bound (rigorous)" if terms.proved
                             else "enclosure where ball arithmetic reaches, else samples: " + ", ".join(f"{t} {h}" for t, h in zip(terms.thetas, terms.how)))}
    return Polytope("Jacobian terms", terms.vertex_matrices(), labels, terms.proved, balls, meta)


#: The most vertices a subdivided term polytope may have (sub-boxes x 2^K corners).
MAX_SUBDIVIDED_VERTICES = 2048
# One end of one term's range on one sub-box is enclosed with the stage's box budget (proofs.max_boxes), as on the
# whole box: a sub-box needs fewer boxes for the same tolerance, and no clock decides how many it gets.


#: A corner is left out of a subdivided polytope only when it lies this far inside every facet of the hull of the
#: corners (in coordinates scaled to the unit box): far beyond the rounding of qhull's facets (1e-15), so the hull
#: of the corners kept contains it, and the LMI at the kept corners implies it there (the LMI is affine in theta).
HULL_INSIDE = 1e-9


#: Above this many terms the corners are all kept: qhull's facets grow like N^(K/2) (9 terms: 8 GiB and 10 minutes
#: for the 512-corner sub-boxes of a 3-pendulum ring).
HULL_MAX_TERMS = 4


def hull_points(points: np.ndarray) -> np.ndarray:
    """The indices of the points on (or within ``HULL_INSIDE`` of) the boundary of their convex hull: the vertices
    the LMI must be imposed at.  A sub-box refinement's corner sets overlap in term space, and most of their corners
    lie inside the hull of the others (256 corners, 30 on the hull, on a levitation plant's two terms): the LMI at an
    interior corner is implied by the rest, and each vertex costs the SDP a cone.

    Parameters
    ----------
    points : ndarray (N, K)
        The corners, one row each, in term values.

    Returns
    -------
    ndarray of int
        Sorted indices of the points kept (all of them when the hull is degenerate, K is 0 or above
        ``HULL_MAX_TERMS``).
    """
    from scipy.spatial import ConvexHull, QhullError

    N, K = points.shape
    if K == 0 or N <= K + 1 or K > HULL_MAX_TERMS:
        return np.arange(N)
    lo, width = points.min(axis=0), np.ptp(points, axis=0)
    if np.any(width <= 0):
        return np.arange(N)             # flat in one term: a hull of lower dimension, kept whole
    unit = (points - lo) / width
    if K == 1:
        return np.flatnonzero((unit[:, 0] <= HULL_INSIDE) | (unit[:, 0] >= 1 - HULL_INSIDE))
    try:
        hull = ConvexHull(unit)
    except QhullError:
        return np.arange(N)
    # qhull's equations: unit normal n and offset c with n . x + c <= 0 inside
    depth = unit @ hull.equations[:, :-1].T + hull.equations[:, -1]
    return np.flatnonzero(depth.max(axis=1) > -HULL_INSIDE)


class SubBoxes:
    """The term polytope over a set of sub-boxes of state_box x U, refined where the LMI binds.

    The terms of one state are correlated (exp(-E/T) and c exp(-E/T)/T^2 both follow T), and one box of their values
    holds combinations no state produces; on small sub-boxes it does not.  The mean value of df/dx along a segment of
    the (convex) box lies in the convex hull of the union of the sub-boxes' corner sets (each sub-box's term ranges
    enclosed by ball arithmetic), so the vertex argument holds for the union as for one box, and the certified rate
    approaches the supremum over the true Jacobians as the sub-boxes shrink.  :meth:`split` halves the sub-boxes
    whose corners bind the LMI for a given (M, lambda), along the coordinate the terms depend on that is widest
    relative to the whole box: the refinement goes where the rate is lost (branch and bound on the state box).
    """

    def __init__(self, model: Model, terms: Terms):
        self.model, self.terms = model, terms
        args = list(model.x) + list(model.u)
        self.args = args
        self.box = np.r_[model.state_box, model.U]
        self.used = sorted({args.index(s) for t in terms.thetas for s in t.free_symbols if s in args})
        self.compiled = [proofs.compile_claims(model, [theta], args) for theta in terms.thetas]
        self.dense = terms.dense()
        self.boxes = [self.box.copy()]
        self._ranges: dict = {}

    def ranges(self, sub: np.ndarray) -> list[tuple[float, float]] | None:
        """The enclosures of every term on one sub-box (cached), or None if one is not finite."""
        key = tuple(map(float, sub.ravel()))
        if key not in self._ranges:
            out = []
            for fun in self.compiled:
                lo, hi, ok = enclose_term(fun, sub)
                if not ok:
                    out = None
                    break
                out.append((lo, hi))
            self._ranges[key] = out
        return self._ranges[key]

    def vertex_count(self) -> int:
        return len(self.boxes) * 2 ** len(self.terms)

    def polytope(self) -> Polytope | None:
        """The union of the sub-boxes' corner sets as a polytope (None if an enclosure fails)."""
        terms, n = self.terms, self.model.n
        corners, owner, seen = [], [], set()
        for b, sub in enumerate(self.boxes):
            ranges = self.ranges(sub)
            if ranges is None:
                return None
            for corner in itertools.product(*ranges):
                # equal corners only, by their exact enclosure values: a term enclosed in [4e-18, 2e-16] times a
                # coefficient of 1e17 spans tens of units of df/dx, so no rounding of the term may merge its ends
                key = tuple(float(v) for v in corner)
                if key not in seen:
                    seen.add(key)
                    corners.append(corner)
                    owner.append(b)
        interior = len(corners)
        keep = hull_points(np.array(corners, dtype=float))
        corners, owner = [corners[k] for k in keep], [owner[k] for k in keep]
        interior -= len(corners)
        matrices = [terms.A0 + sum((t * A for t, A in zip(c, self.dense)), np.zeros_like(terms.A0)) for c in corners]
        labels = [", ".join(f"{t} = {v:.6g}" for t, v in zip(terms.thetas, c)) for c in corners]

        def balls():
            f = proofs.BoxFunction(self.model, {f"A{k}": A for k, A in enumerate(terms.coefficient_matrices(n))}, [])
            parts = f([])
            A0, As = parts["A0"], [parts[f"A{k + 1}"] for k in range(len(terms))]
            return [[[A0[i][j] + sum((proofs.arb(float(t)) * A[i][j] for t, A in zip(c, As)), proofs.arb(0)) for j in range(n)]
                     for i in range(n)] for c in corners]

        names = [str(self.args[d]) for d in self.used]
        meta = {"jacobian_terms": [str(t) for t in terms.thetas], "term_ranges": terms.ranges.tolist(), "ranges_proved": True,
                "subdivision": f"{len(self.boxes)} sub-boxes of state_box x U along {names}, refined where the LMI binds "
                               f"({len(matrices)} vertices of the hull of their corners; {interior} corners inside it left out)",
                "range_method": "ball-arithmetic enclosure of each term on each sub-box by branch and bound (rigorous)"}
        poly = Polytope("Jacobian terms", matrices, labels, True, balls, meta)
        poly.meta["_owner"] = owner
        return poly

    def split(self, poly: Polytope, M: np.ndarray, lam: float, share: float = 0.25) -> bool:
        """Halve the sub-boxes whose worst corner margin of A^T M + M A + lambda M is among the largest (the top
        ``share``, at least one), within the vertex budget; False when nothing more can be split."""
        from ashc_cli.design.contraction.vertex import lmi_margins

        owner = poly.meta["_owner"]
        margins = lmi_margins(poly.matrices, M, lam)
        worst = np.full(len(self.boxes), -np.inf)
        for b, mg in zip(owner, margins):
            worst[b] = max(worst[b], mg)
        room = (MAX_SUBDIVIDED_VERTICES - self.vertex_count()) // 2 ** len(self.terms)
        if room <= 0 or not self.used:
            return False
        # the binding boxes (worst margin within 5% of the rate's scale of 0), at least the top ``share`` of them
        scale = max(abs(lam), 1e-300) * float(np.linalg.eigvalsh(M).max())
        binding = int(np.sum(worst >= -0.05 * scale))
        count = max(1, min(room, max(binding, int(np.ceil(share * len(self.boxes))))))
        chosen = set(np.argsort(-worst)[:count].tolist())
        widths = np.maximum(np.ptp(self.box, axis=1), 1e-300)
        boxes = []
        for b, sub in enumerate(self.boxes):
            if b not in chosen:
                boxes.append(sub)
                continue
            d = max(self.used, key=lambda k: (sub[k, 1] - sub[k, 0]) / widths[k])
            mid = 0.5 * (sub[d, 0] + sub[d, 1])
            left, right = sub.copy(), sub.copy()
            left[d, 1], right[d, 0] = mid, mid
            boxes += [left, right]
        self.boxes = boxes
        return True
