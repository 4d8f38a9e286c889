"""Stage 1: asymptotic stabilisability by a quadratic incremental Lyapunov function (eq. (28), Theorem 1).

V(x, z) = (x - z)^T M (x - z) (eq. (30)) satisfies Theorem 1 with k(z, x, u) = u (or u + K (z - x) with a
synthesised gain) when

    J^T M + M J <= -lambda M,   M > 0                                                   (eq. (28))

for every J the incremental dynamics can meet.  The matrices J range over a polytope (:mod:`ashc_cli.design.contraction.terms`)
and the LMI, affine in J, is imposed at its vertices:

* f = A(u) x + b(u) with A affine in u (eq. (27)): A(u) at the vertices of U;
* f not affine in x, over ``concrete.state_box`` x U (the mean-value form f(x) - f(z) = int J ds (x - z)): the Jacobian
  written as A0 + sum_k theta_k A_k over the plant's distinct nonlinear terms, each theta_k enclosed by ball arithmetic,
  at the corners of the box of term values; and the older box of independent entries, where it is small.  The one that
  certifies the larger rate is used, and recorded (``meta["polytope"]``).

The LMI itself is solved by :mod:`ashc_cli.design.contraction.vertex` (identity feedback) or
:mod:`ashc_cli.design.contraction.feedback` (``feedback: linear_gain``: the smallest gain K the rate allows), on the matrices
divided by the plant's rate scale so that its tolerances are relative, and proved in ball arithmetic by
:mod:`ashc_cli.design.contraction.proof`.
"""

from __future__ import annotations

import dataclasses
import itertools

import numpy as np
import scipy.sparse as sps
import sympy as sp

from ashc_cli.numerics import proofs
from ashc_cli.design.artefacts import Artefact, Check
from ashc_cli.design.contraction.feedback import FEEDBACK_CONDITION, FEEDBACK_MAX_RATE, FEEDBACK_RATE_MARGIN, largest_feedback_rate, solve_lmi_feedback
from ashc_cli.design.contraction.lyapunov import available_memory, distinct, lyapunov_M, refuse_if_too_large, sdp_memory_estimate
from ashc_cli.design.contraction.objective import frontier, gain_estimate, min_gain_M
from ashc_cli.design.contraction.network import BACKOFF as NETWORK_BACKOFF
from ashc_cli.design.contraction.network import largest_rate as network_largest_rate
from ashc_cli.design.contraction.network import network_polytope
from ashc_cli.design.contraction.network import prove as prove_network
from ashc_cli.design.contraction.proof import prove_lmi
from ashc_cli.design.contraction.precheck import refute_rate
from ashc_cli.design.contraction import given
from ashc_cli.design.contraction.structured import structured_M
from ashc_cli.design.contraction.terms import (MAX_VARYING_ENTRIES, MAX_VERTEX_TERMS, Polytope, affine_polytope, decompose, entry_polytope,
                                 jacobian_samples, refuse_jumps, SubBoxes, term_polytope)
from ashc_cli.design.contraction.vertex import (BISECTION_RTOL, FULL_MAX_STATES, M_MIN_EIG, MARGIN_TOL, SCALE_FREE_MARGIN, certify_rate,  # noqa: F401
                                  infeasible_from, largest_decay_rate, largest_decay_rate_for, lmi_margins, lmi_scale, solve_lmi,
                                  structures, sweep, vertices)
from ashc_cli.errors import DesignError, NumericalError, SpecError
from ashc_cli.problem.grids import domain_grid
from ashc_cli.problem.model import Model, jumps, nonzero_entries, sparse_jacobian, tidy
from ashc_cli.design.upstream import dp_function

NAME = "stabilise"
UPSTREAM: tuple[str, ...] = ()
#: Points of V on which the smallest-gain objective measures dbar (per abstract state: 65, then 17 x 17, ...).
GAIN_GRID = {1: 65, 2: 17 ** 2, 3: 7 ** 3}


def upstream(spec) -> tuple[str, ...]:
    """The manifold for ``objective: min_gain`` (dbar needs dp/dxi), else nothing: the first box of the flow chart.

    Parameters
    ----------
    spec : Spec
        The spec (``stabilisability.objective`` is read).

    Returns
    -------
    tuple of str
    """
    return ("manifold",) if spec.stabilisability.objective == "min_gain" else ()


def reads(spec) -> tuple[str, ...]:
    """The spec keys this stage reads: the concrete plant, the stabilisability keys and the proofs' budgets (and the
    abstract names, stored for ``ashc eval``); the whole abstraction and interface for ``objective: min_gain``, which
    measures dbar on V.  Editing anything else (abstract.p, a task, a scenario) keeps its artefact up to date.

    Parameters
    ----------
    spec : Spec
        The spec (``stabilisability.objective`` is read).

    Returns
    -------
    tuple of str
        Dotted spec keys.
    """
    base = ("parameters", "concrete", "stabilisability", "proofs", "abstract.states", "abstract.inputs")
    return base + (("abstract", "interface") if spec.stabilisability.objective == "min_gain" else ())


def _other_choices(model: Model, st, poly) -> str:
    """What a spec may change when no M certifies the rate: only choices the tool accepts for this plant
    (``feedback: linear_gain`` needs f affine in u with a constant g, and is no help once chosen)."""
    varies = len({np.asarray(A, dtype=float).tobytes() for A in poly.matrices}) > 1     # one vertex: no set to shrink
    choices = [] if not varies else ["a smaller concrete.input_bounds (A(u) is taken at the corners of U)" if poly.kind == "affine in u"
                                     else "a smaller concrete.state_box (the ranges are taken over all of it, each independently)"]
    return "".join(f", or {c}" for c in choices) + _linear_gain_choice(model, st)


def _linear_gain_choice(model: Model, st) -> str:
    """", or feedback: linear_gain ..." where the tool accepts it (f input-affine with a constant g, not chosen yet)."""
    if st.feedback != "linear_gain" and _gain_accepted(model):
        return ", or feedback: linear_gain (g constant) to synthesise a stabilising K"
    return ""


def _gain_accepted(model: Model) -> bool:
    """Whether ``feedback: linear_gain`` applies: f input-affine with a g that does not depend on x."""
    return model.affine and not any(e.free_symbols & set(model.x) for e in model.g)


def affine_form(model: Model, J: sp.Matrix | None = None) -> tuple[sp.Matrix, sp.Matrix]:
    """Write f(x, u) = A(u) x + b(u) symbolically (eq. (27)).

    ``J``, if given, is df/dx already computed (A is that Jacobian when f is affine in x).

    Parameters
    ----------
    model : Model
        The spec's systems (f, x, u).
    J : sympy Matrix (n, n), optional
        df/dx; computed from f when None.

    Returns
    -------
    A, b : sympy Matrix
        A(u) (n x n, affine in u) and b(u) (n x 1).

    Raises
    ------
    DesignError
        If f is not affine in x, or A is not affine in u.
    """
    A = sparse_jacobian(model.f, model.x) if J is None else J
    xs, us = set(model.x), list(model.u)
    for (i, j), e in nonzero_entries(A).items():
        if e.free_symbols & xs:
            raise DesignError("concrete", f"f(x, u) is not affine in x: df{i + 1}/d{model.x[j]} = {e} depends on x",
                              "f(x, u) = A(u) x + b(u) for stabilisability.method polytopic_lmi or given")
        if not _affine_in(e, us):
            raise DesignError("concrete", f"A(u) is not affine in u: entry ({i + 1}, {j + 1}) = {e}",
                              "A(u) affine in u so that the LMI at the vertices of U covers all of U")
    b = tidy(sp.expand(model.f - A * model.x))
    for i, e in enumerate(b):
        if e.free_symbols & xs:
            raise DesignError("concrete", f"f(x, u) is not affine in x: f{i + 1} - (A x){i + 1} = {e} depends on x (a jump such as sign(x) has a zero "
                              "derivative almost everywhere but is not affine)",
                              "f(x, u) = A(u) x + b(u), or a concrete.state_box on which f is Lipschitz and C^1 almost everywhere")
    return tidy(A), b


def _depends_on_x(model: Model, J: sp.Matrix) -> bool:
    """Whether df/dx depends on the states (or f has a jump in them, whose Jacobian is free of x almost everywhere)."""
    xs = set(model.x)
    return any(e.free_symbols & xs for e in nonzero_entries(J).values()) or jumps(model.f, model.x)


def _u_only(model: Model, J: sp.Matrix) -> bool:
    """df/dx free of x but not affine in u (x' = -exp(u) x + u): the vertices of U do not bound it, and the term
    polytope over U does (the states do not enter, so the certificate holds for every x)."""
    return not _depends_on_x(model, J) and not all(_affine_in(e, list(model.u)) for e in nonzero_entries(J).values())


def _affine_in(e: sp.Expr, us: list) -> bool:
    """Whether e is affine in the symbols us (every second derivative zero; simplify only what is not plainly zero)."""
    if not e.free_symbols.intersection(us):
        return True
    for a, b in itertools.product(us, us):
        second = sp.diff(e, a, b)
        if second != 0 and sp.simplify(second) != 0:
            return False
    return True


#: The term polytope is refined (its sub-box grid doubled) while the certified rate grows by more than this.
REFINE_GAIN = 0.02


def polytopes(model: Model, J: sp.Matrix) -> tuple[list[Polytope], sp.Matrix, sp.Matrix]:
    """The polytopes the LMI may be imposed on, best first, with A and b for the artefact.

    f affine in x: A(u) at the vertices of U.  Otherwise the term polytope (at most MAX_VERTEX_TERMS terms) and the
    entry polytope (at most MAX_VARYING_ENTRIES entries), both over state_box x U.

    Parameters
    ----------
    model : Model
        The spec's systems (f, U, ``state_box``).
    J : sympy Matrix (n, n)
        df/dx, in x and u.

    Returns
    -------
    polytopes : list of Polytope
        At least one.
    A, b : sympy Matrix
        A(u) and b(u) of eq. (27) on the affine path (no ``state_box``, or f affine in x without jumps); else J and
        an n x 1 zero.

    Raises
    ------
    DesignError
        If f has a jump in the box, or no polytope is small enough to enumerate.
    """
    # (a sign of a state has a Jacobian free of x almost everywhere, but f is not affine: its jump needs the box)
    affine = (model.state_box is None or not _depends_on_x(model, J)) and not _u_only(model, J)
    if affine:
        A_sym, b_sym = affine_form(model, J)
        return [affine_polytope(model, A_sym, vertices(model.U))], A_sym, b_sym
    refuse_jumps(model)
    found = []
    decomposition = decompose(model, J)
    if len(decomposition) <= MAX_VERTEX_TERMS:
        found.append(term_polytope(model, decomposition))
        found[-1].meta["_terms"] = decomposition
    network = network_polytope(model, decomposition)
    if network is not None:
        # a network of dissipative terms: a diagonal M found from the terms, a rate from an eigenvalue (any size)
        network[0].meta["_terms"] = decomposition
        found.insert(0 if len(decomposition) > MAX_VERTEX_TERMS else len(found), network[0])
    args = set(model.x) | set(model.u)
    entries = sum(1 for e in nonzero_entries(J).values() if e.free_symbols & args)
    if entries <= MAX_VARYING_ENTRIES and entries != len(decomposition):
        found.append(entry_polytope(model, J))
    if not found:
        raise DesignError("concrete", f"df/dx has {len(decomposition)} distinct nonlinear terms and {entries} varying entries over the state box "
                          f"(at most {MAX_VERTEX_TERMS} terms or {MAX_VARYING_ENTRIES} entries are enumerated as vertices)",
                          "df/dx with fewer distinct state-dependent terms (a term that varies little written as a constant), or f affine "
                          "in x", check="lmi_margin")
    return found, J, sp.zeros(model.n, 1)


def run(model: Model, upstream: dict[str, Artefact]) -> Artefact:
    """Certify stabilisability: M and lambda of eq. (28), with margins re-checked in numpy and proved; M defines
    V(x, z) = (x - z)^T M (x - z) of eq. (30).

    Parameters
    ----------
    model : Model
        The spec's systems.
    upstream : dict
        Unused (the first stage).

    Returns
    -------
    Artefact
        Values M, K, lambda, vertex and sweep margins, lmi_margin; expressions A (A(u) or df/dx) and b.

    Raises
    ------
    DesignError
        If f is not of the class the method needs, M is not positive definite, or the LMI is infeasible at the
        requested decay rate (the message names the least stable vertex and the largest rate the solver certifies).
    NumericalError
        If the solver claims success but the numpy re-check fails.
    """
    st = model.spec.stabilisability
    J = sparse_jacobian(model.f, model.x)
    u_only = _u_only(model, J)
    if u_only and model.state_box is None:
        # df/dx reads u alone: its terms are enclosed over U, the (absent) state box any point
        model = dataclasses.replace(model, state_box=np.zeros((model.n, 2)))
    if st.feedback == "identity" or _gain_accepted(model):
        # a sampled state where no M (no K) can work: refused in seconds, before the enclosures and the SDP
        refute_rate(model, J, 0.0 if st.decay_rate == "maximise" else float(st.decay_rate), _linear_gain_choice(model, st))
    if st.method == "given":
        return _given(model, st, J)
    try:
        candidates, A_sym, b_sym = polytopes(model, J)
    except DesignError as exc:
        if not _too_many_terms(exc) or st.objective != "rate":
            raise
        return _automatic_norm_bound(model, st, J, exc)
    if st.feedback == "linear_gain" and not model.affine:
        raise DesignError("stabilisability.feedback", "linear_gain needs an input-affine plant with a constant g, and concrete.f is not affine in the inputs",
                          "feedback identity (k(x, z, u) = u: the interface applies l(xi))", check="lmi_margin")
    if st.feedback == "linear_gain" and any(e.free_symbols & set(model.x) for e in model.g):
        raise DesignError("concrete.g", "feedback linear_gain needs a constant input matrix g (the closed loop's g(z) K would vary with the state)",
                          "g independent of x, or feedback identity", check="lmi_margin")
    results, first_failed = [], None
    for poly in candidates:
        try:
            # explained (with the bisection for the largest rate a hint names) only if nothing certifies, below
            results.append((poly, *_certify(model, st, poly, explain=False)))
        except DesignError:
            first_failed = first_failed or poly
            continue
        if st.decay_rate != "maximise":
            break                      # a fixed rate: the first polytope that certifies it
    terms_found = next((p.meta.get("_terms") for p in candidates if p.kind == "Jacobian terms"), None)
    if terms_found is not None and (st.decay_rate == "maximise" or not results):
        results += _refine(model, st, terms_found, results)
    if not results and st.objective == "rate" and not any(p.kind in ("affine in u", "Jacobian terms", "Jacobian entries") for p in candidates):
        # only the network certificate was tried (too many terms to enumerate): the norm-bound test before refusing
        refused = DesignError("stabilisability", "the network certificate gives no decay rate")
        try:
            _certify(model, st, first_failed)
        except DesignError as exc:
            refused = exc
        return _automatic_norm_bound(model, st, J, DesignError(refused.where, f"{refused.what} (df/dx has too many terms to enumerate "
                                                                                "its vertices)", refused.expected))
    if not results:
        _certify(model, st, first_failed)          # raises, with the hint the refusal needs
    poly, M, K, lam, meta = max(results, key=lambda r: r[3])
    if st.objective == "min_gain":
        M, lam, meta = _min_gain(model, st, poly, upstream, M, lam, meta)
    meta.update(method=st.method, feedback=st.feedback, polytope=poly.kind, vertices_count=len(poly.matrices),
                polytopes_tried=[p.kind for p in candidates], **{k: v for k, v in poly.meta.items() if not k.startswith("_")})
    if u_only:
        meta["condition"] = "df/dx(u)^T M + M df/dx(u) <= -lambda M for u in U (" + poly.kind + " over U; df/dx does not depend on x: every state)"
    elif poly.kind != "affine in u":
        # The certificate holds while x stays in the box: the bound stage's region reads this key.
        meta["condition"] = "J(x, u)^T M + M J(x, u) <= -lambda M on state_box x U (" + poly.kind + ")"
        meta["state_box"] = model.state_box.tolist()
    return _artefact(model, st, poly, A_sym, b_sym, M, K, lam, meta)


def _too_many_terms(exc: DesignError) -> bool:
    """Whether :func:`polytopes` refused df/dx for having too many terms and entries to enumerate as vertices."""
    return exc.where == "concrete" and "distinct nonlinear terms" in exc.what


def _automatic_norm_bound(model: Model, st, J: sp.Matrix, refused: DesignError) -> Artefact:
    """``polytopic_lmi`` on a df/dx with too many terms to enumerate: M from the Lyapunov equation of the linearisation
    (and K by LQR with ``linear_gain``), proved by the norm-bound test (:func:`_given`), the choice recorded."""
    auto = st.model_copy(update={"M": "lyapunov", "K": "lqr" if st.feedback == "linear_gain" else None})
    try:
        art = _given(model, auto, J)
    except DesignError as exc:
        largest = getattr(exc, "largest_rate", None)
        if largest is None:
            raise           # not the test's rate (g not constant, df/dx not enclosed, ...): its own words
        how = (f"proves lambda = {largest:.6g} at most, below the decay_rate {st.decay_rate}" if largest > 0 else
               f"proves no positive rate (the largest it allows is {largest:.6g})")
        hint = "a smaller concrete.state_box, a stabilisability.linearise_at nearer the operating point, or method: given with your M (and K)"
        raise DesignError("stabilisability", f"{refused.what}; the norm-bound test with M from the Lyapunov equation of the linearisation "
                          f"(or the identity){' and K by LQR' if st.feedback == 'linear_gain' else ''} {how}",
                          (f"decay_rate <= {largest:.6g} (or maximise), " if largest > 0 else "") + hint, check="lmi_margin") from None
    art.meta["route"] = "automatic: " + art.meta["route"] + (", M from the Lyapunov equation of the linearisation"
                                                            + (", K by LQR" if st.feedback == "linear_gain" else ""))
    return art


def _given(model: Model, st, J: sp.Matrix) -> Artefact:
    """``method: given`` (:mod:`ashc_cli.design.contraction.given`): M and K from the spec or the linearisation, the
    largest rate they certify on the first polytope when df/dx has few enough terms to enumerate (the vertex
    argument, exact), else by the norm-bound test (one enclosure per entry); ``maximise`` takes that rate."""
    x0, u0 = given.linearisation_point(model, st)
    A0 = given.linearise(model, J, x0, u0)
    B = given.input_matrix(model) if st.feedback == "linear_gain" else np.zeros((model.n, model.m))
    K = given.gain(st, A0, B) if st.feedback == "linear_gain" else np.zeros((model.m, model.n))
    try:
        candidates, A_sym, b_sym = polytopes(model, J)
        why = "df/dx has too many terms to enumerate its vertices; the network certificate holds for its own diagonal M only"
    except DesignError as exc:
        if not _too_many_terms(exc):
            raise
        candidates, why = [], exc.what
    # a hull of every df/dx (not the network's lower corners, which bound the LMI for its own diagonal M only)
    hulls = [p for p in candidates if "_network" not in p.meta]
    if hulls:
        poly = hulls[0]
        M, shift = given.metric(st, A0 + B @ K)
        lam_max = largest_decay_rate_for([np.asarray(A.toarray() if hasattr(A, "toarray") else A) + B @ K for A in poly.matrices], M)
        route = f"the vertices of the {poly.kind} polytope (exact)"
    else:
        nb = given.norm_bound(model, J, A0)
        poly = given.norm_polytope(nb, f"chosen because {why}")
        A_sym, b_sym = J, sp.zeros(model.n, 1)
        M, shift = given.metric(st, nb.A0 + B @ K, nb, B @ K)      # lyapunov: of the middle of the enclosures
        lam_max = given.largest_rate(nb, M, B @ K)
        route = "the norm-bound test (df/dx has too many terms to enumerate its vertices)"
    # maximise: a little below the largest rate, so that the proof sees a strictly negative margin
    lam = lam_max * (1 - given.BACKOFF) if st.decay_rate == "maximise" else float(st.decay_rate)
    if lam > lam_max * (1 + 1e-12) or lam_max <= 0:
        what = f"does not satisfy eq. (28) at any positive decay rate by {route} (the largest lambda it allows is {lam_max:.6g})" if lam_max <= 0 else \
            f"does not satisfy eq. (28) at lambda = {lam:g} by {route} (the largest rate it certifies is {lam_max:.6g})"
        refusal = DesignError("stabilisability.M", what,
                              f"a decay_rate <= {lam_max:.6g}" if lam_max > 0 else
                              "another M or K (lyapunov, lqr, another linearise_at)" + (", or a smaller concrete.state_box" if poly.kind != "affine in u" else ""),
                              check="lmi_margin")
        refusal.largest_rate = lam_max          # read by _automatic_norm_bound, which words its own refusal
        raise refusal
    meta = {"solver": "none (M given; verified in numpy)" if shift is None else
            ("none: M = I (the norm-bound test proves more with it than with the Lyapunov solutions)" if shift == 0.0 else
             f"none: M from the Lyapunov equation of A0 + B K shifted by {shift:.6g} (scipy)"), "route": route,
            "linearise_at": {"x": x0.tolist(), "u": u0.tolist()}, "largest_rate_certified": lam_max,
            "K_source": "given" if isinstance(st.K, list) else ("lqr (Q = I, R = I)" if st.K == "lqr" else "none (identity feedback)")}
    if J.free_symbols & set(model.x) and poly.kind != "affine in u":
        meta["condition"] = "J(x, u)^T M + M J(x, u) <= -lambda M on state_box x U (" + poly.kind + ")"
        meta["state_box"] = model.state_box.tolist()
    meta.update(method=st.method, feedback=st.feedback, polytope=poly.kind, vertices_count=len(poly.matrices),
                **{k: v for k, v in poly.meta.items() if not k.startswith("_")})
    return _artefact(model, st, poly, A_sym, b_sym, M, K, lam, meta)


def _refine(model: Model, st, decomposition, results: list) -> list:
    """Certificates on the term polytope over sub-boxes of state_box x U refined where the LMI binds
    (:class:`SubBoxes`): for ``maximise`` while the rate grows by more than REFINE_GAIN over two rounds, for a fixed
    rate until it is certified; both stop at the vertex budget."""
    try:
        grid = SubBoxes(model, decomposition)
    except proofs.interval.UnsupportedExpression:
        return []
    found, history = [], []
    # the first refinement is uniform (every used coordinate halved once) so that binding boxes can be told apart
    for _ in grid.used:
        poly = grid.polytope()
        if poly is None or not grid.split(poly, np.eye(model.n), 0.0, share=1.0):
            break
    while True:
        poly = grid.polytope()
        if poly is None:
            return found
        try:
            last = (poly, *_certify(model, st, poly, explain=False))
            found.append(last)
        except DesignError:
            last = None
        if last is not None and st.decay_rate != "maximise":
            return found
        if last is not None:
            history.append(last[3])
            # stop when three rounds together gained less than REFINE_GAIN
            if len(history) > 3 and history[-1] <= history[-4] * (1 + REFINE_GAIN):
                return found
        M, lam = (last[1], last[3]) if last is not None else (np.eye(model.n), float(st.decay_rate) if st.decay_rate != "maximise" else 0.0)
        if not grid.split(poly, M, lam, share=0.25 if last is not None else 1.0):
            return found


def _certify(model: Model, st, poly: Polytope, explain: bool = True) -> tuple[np.ndarray, np.ndarray, float, dict]:
    """M, K and lambda on one polytope (M given, searched, or with a synthesised gain), and what was done.  Without
    ``explain`` (a refinement round, whose failure only means "refine further") a failure skips the bisection for the
    largest certifiable rate that only the hint of a final refusal needs."""
    meta: dict = {}
    K = np.zeros((model.m, model.n))
    if "_network" in poly.meta:
        if st.feedback == "linear_gain" or st.method == "given":
            raise DesignError("stabilisability", "the network certificate finds its own diagonal M (identity feedback, polytopic_lmi)",
                              "feedback identity and method polytopic_lmi", check="lmi_margin")
        M, lam, meta = _network_rate(model, st, poly, meta)
        return M, K, lam, meta
    # The LMI is solved on A / s, s the largest spectral radius (rates divided by s too; M and K are unchanged), so
    # that its tolerances are relative to the plant's own time scale: a plant in nanoseconds or in days is solved
    # as one in seconds.
    scale = lmi_scale(poly.matrices)
    scaled = [A / scale for A in poly.matrices]
    meta["lmi_scale"] = scale
    if st.feedback == "linear_gain":
        M, K, lam, meta = _synthesise_feedback(model, st, scaled, meta, poly, scale, explain)
    elif model.n > FULL_MAX_STATES and st.decay_rate != "maximise" and (found := structured_M(scaled, float(st.decay_rate) / scale, st.structure)) is not None:
        # a large plant: the metric its structure gives (the stored energy of a ladder) checked by an eigenvalue, no SDP
        M, name, tried = found
        lam = float(st.decay_rate)
        meta.update(solver=f"none: M = {name}, checked by the generalised eigenvalue at every vertex (no SDP)",
                    structure="diagonal" if not np.any(M - np.diag(np.diag(M))) else "full",
                    structured_candidates=[[t, r * scale] for t, r in tried])
    elif model.n > FULL_MAX_STATES and (found := _lyapunov(model, st, scaled, scale)) is not None:
        M, lam, how = found
        meta.update(solver="none: M from the Lyapunov equation (A + lambda/2 I)^T M + M (A + lambda/2 I) = -I (scipy, no SDP)",
                    structure="full", lyapunov=how)
    else:
        meta.update(solver="CLARABEL via cvxpy", normalisation=f"trace(M) = n (and M >= {M_MIN_EIG} I in the maximum-margin problem)",
                    objective="minimise t subject to A_k^T M + M A_k + lambda M <= t I at every vertex A_k",
                    margin_tol=MARGIN_TOL,
                    fallback=f"when that does not certify lambda: minimise kappa subject to I <= M <= kappa I and A_k^T M + M A_k + lambda M "
                             f"<= -{SCALE_FREE_MARGIN:g} kappa I, accepted when the numpy margin over ||M|| is below -{MARGIN_TOL:g}; M scaled to trace(M) = n")
        M, lam, meta = _search(scaled, st, structures(st.structure, model.n), meta, model, poly, scale, explain)
    return M, K, lam, meta


def _min_gain(model: Model, st, poly: Polytope, upstream: dict, M_rate: np.ndarray, lam_rate: float, meta: dict):
    """``objective: min_gain`` (:mod:`ashc_cli.design.contraction.objective`): the M of the smallest gain G at the decay rate,
    or the (lambda, M) of the smallest G on the lambda-G frontier below the largest certified rate for ``maximise``.
    The rate-optimal M and its G estimate are kept in the meta for comparison."""
    if st.feedback != "identity" or st.method != "polytopic_lmi" or "_network" in poly.meta:
        raise SpecError("stabilisability.objective", f"'min_gain' with feedback {st.feedback}, method {st.method}"
                        f"{' and a network certificate' if '_network' in poly.meta else ''}",
                        "min_gain with feedback identity and method polytopic_lmi (the vertex LMI)")
    if model.delta is None:
        raise SpecError("stabilisability.objective", "'min_gain' with abstract.delta: flatten (flatten designs delta from M)",
                        "an explicit abstract.delta (or identity) with min_gain")
    man = upstream["manifold"]
    grid = domain_grid(model.V, GAIN_GRID.get(model.n_hat, 4 ** model.n_hat))
    dp = np.asarray(dp_function(man, model)(*grid), dtype=float)                        # (n, n_hat, N)
    delta = np.broadcast_to(np.asarray(model.numeric(model.delta, list(model.xi))(*grid), dtype=float), (model.n_hat, model.m_hat, grid.shape[1]))
    W = []
    for j in range(grid.shape[1]):              # distinct values only (an affine p with a constant delta has one)
        w = dp[:, :, j] @ delta[:, :, j]
        if not any(np.array_equal(w, other) for other in W[-8:]):
            W.append(w)
    C = model.C
    L_h = None if C is not None else float(model.h_jacobian_bound()[0])
    scale = lmi_scale(poly.matrices)
    scaled = [A / scale for A in poly.matrices]
    # A full M where it fits (a chain needs its position-velocity couplings; a diagonal M certifies no rate there)
    structure = "diagonal" if st.structure == "diagonal" else "full"
    if structure == "full" and sdp_memory_estimate(model.n, len(distinct(scaled)), "full") > 0.8 * available_memory():
        structure = "diagonal"
    refuse_if_too_large(model.n, len(distinct(scaled)), structure)
    rate_gain = gain_estimate(M_rate, lam_rate, W, C, L_h)
    if st.decay_rate == "maximise":
        points = [(lam * scale, g, Mv) for lam, g, Mv in frontier(scaled, lam_rate / scale, W, C, structure, L_h)]
        points = [(lam, gain_estimate(Mv, lam, W, C, L_h), Mv) for lam, _, Mv in points]
        if not points:
            return M_rate, lam_rate, meta
        lam, gain, M = min(points, key=lambda q: q[1])
        meta.update(objective_frontier=[[float(a), float(b)] for a, b, _ in points])
    else:
        lam = float(st.decay_rate)
        M, _ = min_gain_M(scaled, lam / scale, W, C, structure)
        if M is None:
            return M_rate, lam_rate, meta
        gain = gain_estimate(M, lam, W, C, L_h)
    if gain >= rate_gain:
        lam, gain, M = lam_rate, rate_gain, M_rate
    M = model.n * M / np.trace(M)
    meta.update(objective="min_gain: minimise max_j ||sqrt(M) dp/dxi delta (xi_j)||^2 on a grid of V subject to eq. (28) and alpha_h >= 1",
                gain_estimate=gain, rate_objective_lambda=lam_rate, rate_objective_gain_estimate=rate_gain, structure=structure,
                solver="CLARABEL via cvxpy (smallest gain)")
    return M, lam, meta


def _lyapunov(model: Model, st, scaled: list[np.ndarray], scale: float) -> tuple[np.ndarray, float, str] | None:
    """M from the Lyapunov equation (:mod:`ashc_cli.design.contraction.lyapunov`) when it certifies every vertex: always for one
    distinct A (then the rate is (1 - BISECTION_RTOL) lambda_sup for ``maximise``), for several when the M of their
    mean happens to certify them all (else None, and the SDP decides)."""
    uniq = distinct(scaled)
    sup = min(-2.0 * float(np.linalg.eigvals(A).real.max()) for A in uniq)
    if not sup > 0:
        return None
    lam = (1.0 - BISECTION_RTOL) * sup if st.decay_rate == "maximise" else float(st.decay_rate) / scale
    if not lam < sup:
        return None
    centre = uniq[0] if len(uniq) == 1 else sum(uniq) / len(uniq)
    M = lyapunov_M(centre, lam)
    if M is None or lmi_margins(uniq, M, lam).max() >= 0:
        return None
    how = "one distinct A" if len(uniq) == 1 else f"the mean of {len(uniq)} distinct vertices, checked at each"
    return M, lam * scale, how


def _network_rate(model: Model, st, poly: Polytope, meta: dict) -> tuple[np.ndarray, float, dict]:
    """M = diag(d) of the network (:mod:`ashc_cli.design.contraction.network`) and the largest rate it certifies at every corner."""
    net = poly.meta["_network"]
    rate = min(network_largest_rate(A if not isinstance(A, np.ndarray) else sps.csr_matrix(A), net.d) for A in poly.matrices)
    best = rate * (1 - NETWORK_BACKOFF)
    if st.decay_rate == "maximise":
        lam = best
    else:
        lam = float(st.decay_rate)
        if not lam <= best:
            raise DesignError("stabilisability.decay_rate", f"the network certificate (diagonal M of the dissipative terms) reaches lambda = {best:.6g} "
                              f"only, below the requested {lam:g}", f"decay_rate below {best:.6g}, or 'maximise'", check="lmi_margin")
    if not lam > 0:
        raise DesignError("stabilisability", f"the network certificate (diagonal M of the dissipative terms) gives no decay rate (largest {rate:.4g})",
                          "a network whose linear part is stable with every term at its lower end", check="lmi_margin")
    M = np.diag(net.d)
    meta.update(solver="none: M from the terms (M b_k = -gamma_k c_k), lambda from a sparse eigenvalue", structure="diagonal",
                network_rate=rate)
    return M, lam, meta


def _artefact(model: Model, st, poly: Polytope, A_sym: sp.Matrix, b_sym: sp.Matrix, M: np.ndarray, K: np.ndarray, lam: float,
              meta: dict) -> Artefact:
    """Re-check the certificate in numpy (vertices, and a sweep of U or samples of the box), prove it, and store it."""
    B_K = np.array(model.substitute(model.g), dtype=float) @ K if st.feedback == "linear_gain" else 0.0
    vertex_margins = lmi_margins([np.asarray(A.toarray() if hasattr(A, "toarray") else A) + B_K for A in poly.matrices], M, lam)
    if poly.kind == "affine in u":
        A_num = model.numeric(A_sym, list(model.u))
        sweep_u = sweep(model.U)
        A_sweep = np.broadcast_to(A_num(*sweep_u.T), (model.n, model.n, len(sweep_u)))   # one vectorised call
        sweep_margins = lmi_margins([A_sweep[:, :, k] + B_K for k in range(len(sweep_u))], M, lam)
    else:
        sweep_u = np.zeros((0, model.m))
        samples, where = jacobian_samples(model, A_sym)
        sweep_margins = lmi_margins([A + B_K for A in samples], M, lam)
        if sweep_margins.max() > 0:
            # A point of the box whose Jacobian breaks the LMI: the (sampled) ranges missed it, and no M found on
            # them certifies the plant. A counter-example, not a solver failure.
            k = int(np.argmax(sweep_margins))
            x_at, u_at = where[k, :model.n], where[k, model.n:]
            raise DesignError("stabilisability", f"eq. (28) fails at x = {np.round(x_at, 6).tolist()}, u = {np.round(u_at, 6).tolist()} "
                              f"(margin {sweep_margins[k]:.3g} > 0 at lambda = {lam:.6g}): its Jacobian lies outside the sampled ranges "
                              f"({meta.get('range_method', '')})", "ranges that ball arithmetic can enclose, or a smaller state_box",
                              check="lmi_margin")
    margin = float(max(vertex_margins.max(), sweep_margins.max()))
    eig_M = np.linalg.eigvalsh(M)
    meta.update(M_condition_number=float(eig_M.max() / eig_M.min()) if eig_M.min() > 0 else None)
    if margin > 0:
        raise NumericalError(NAME, f"the solver reported a solution but the numpy re-check finds margin {margin:.3g} > 0", "a certified M (margin <= 0)")

    if "_network" in poly.meta:
        proved_margin, proof = prove_network(model, poly.meta["_terms"], poly.meta["_network"], lam)
    elif "_normbound" in poly.meta:
        proved_margin, proof = given.prove(model, poly.meta["_normbound"], M, K if st.feedback == "linear_gain" else np.zeros_like(K), lam)
    else:
        proved_margin, proof = prove_lmi(model, poly, K, M, lam)
    margin_evidence = proofs.PROVED if proved_margin <= 0 else proofs.SAMPLED
    if not np.any(M - np.diag(np.diag(M))):
        M_lower = float(np.diag(M).min())          # a diagonal M of exact doubles: its eigenvalues are its entries
    else:
        M_lower = proofs.lambda_min_lower(M) if model.n <= proofs.MAX_PROOF_STATES else -np.inf
    meta.update(lmi_proof=proof if proved_margin <= 0 else f"not proved: {proof} (bound {proved_margin:.3g})")

    art = Artefact(stage=NAME, meta=meta)
    art.values.update({
        "lmi_margin_proved": proved_margin, "M_min_eigenvalue_proved": M_lower,
        "M": M, "K": K, "lambda": lam, "vertex_margins": vertex_margins, "sweep_u": sweep_u,
        "sweep_margins": sweep_margins, "lmi_margin": margin, "M_eigenvalues": eig_M,
        "A_vertices": np.stack([np.asarray(A.toarray() if hasattr(A, "toarray") else A) for A in poly.matrices]) if model.n <= 400 else np.zeros((0, model.n, model.n)),
        "relative_margin": margin / eig_M.max(),
        "vertex_labels": list(poly.labels),
    })
    art.exprs.update({"A": A_sym, "b": b_sym})
    if margin_evidence == proofs.PROVED:
        art.checks["lmi_margin"] = Check(proved_margin, True, "proved upper bound of the largest eigenvalue of A_cl^T M + M A_cl + lambda M, A_cl = A + B K "
                                         f"(K = 0 for identity feedback; <= 0: eq. (28) holds): {proof}", proofs.PROVED)
    else:
        art.checks["lmi_margin"] = Check(margin, margin <= 0, "largest eigenvalue of A_cl^T M + M A_cl + lambda M over the vertices and a sweep (or samples), "
                                         f"A_cl = A + B K (K = 0 for identity feedback; <= 0: eq. (28) holds); proof: {meta['lmi_proof']}")
    if M_lower > 0:
        art.checks["M_positive"] = Check(M_lower, True, "proved lower bound of the smallest eigenvalue of M (> 0; arb Cholesky)", proofs.PROVED)
    else:
        art.checks["M_positive"] = Check(float(eig_M.min()), bool(eig_M.min() > 0), "smallest eigenvalue of M (> 0; numpy)")
    return art


def _search(A_vertices: list[np.ndarray], st, tries: list[str], meta: dict, model: Model, poly: Polytope, scale: float = 1.0,
            explain: bool = True) -> tuple[np.ndarray, float, dict]:
    """M and lambda of eq. (28) (identity feedback), trying each structure of M in turn.

    ``A_vertices`` are divided by ``scale`` (so are the rates inside; the lambda returned is in the plant's units).
    A later structure is tried only when the earlier one finds no M (at the requested rate, or with any
    positive rate for ``maximise``); ``meta["structure"]`` records the one used and ``meta["tried"]`` all.
    """
    tried = []
    for structure in tries:
        tried.append(structure)
        # never start an SDP that cannot fit: a one-line refusal with the estimate instead of being killed
        refuse_if_too_large(model.n, len(distinct(A_vertices)), structure)
        if st.decay_rate == "maximise":
            how: dict = {}
            lam, M = largest_decay_rate(A_vertices, structure=structure, info=how)
            if M is not None:
                meta.update(structure=structure, tried=tried, bisection_rtol=BISECTION_RTOL,
                            bisection_bracket=[lam * scale, float(how["upper_bound"]) * scale], **_formulation_meta(how))
                return M, lam * scale, meta
            continue
        lam = float(st.decay_rate)
        M, t, status, info = certify_rate(A_vertices, lam / scale, structure)
        if M is not None:
            meta.update(structure=structure, tried=tried, status=status, optimal_margin=t * scale, **_formulation_meta(info))
            return M, lam, meta
    worst = _worst_vertex_text(poly, A_vertices, scale)
    other = _other_choices(model, st, poly)
    # The eigenvalues bound every rate from above (Re eig(A_k) <= -lambda / 2); below that bound the solver's
    # failure to find an M is not a proof that none exists (an M may have to be very ill-conditioned).
    eig_bound = min(-2.0 * float(np.linalg.eigvals(A).real.max()) for A in A_vertices) * scale
    unproved = (f"; the eigenvalues allow rates up to {eig_bound:.6g}, so an M may exist that the solver could not reach "
                f"(very ill-conditioned): a given M (method: given) is verified exactly") if eig_bound > 0 else ""
    if st.decay_rate == "maximise":
        what = "no M certifies any decay rate lambda > 0" if eig_bound <= 0 else "the solver found no M certifying a decay rate lambda > 0"
        raise DesignError("stabilisability", f"{what} (eq. (28)){worst}{unproved}",
                          f"a plant that is incrementally stable on the set{other}", check="lmi_margin")
    if not explain:
        raise DesignError("stabilisability.decay_rate", f"the LMI of eq. (28) is infeasible at lambda = {lam:g} on this polytope", "a finer one")
    best, _ = largest_decay_rate(A_vertices, structure=tries[-1])
    hint = (f"decay_rate below {best * scale:.6g} (the largest the solver certifies), or 'maximise'" if best > 0
            else f"a plant that is incrementally stable on the set{other}")
    margin = f"best margin {t * scale:.3g}" if np.isfinite(t) else "no solution"
    raise DesignError("stabilisability.decay_rate", f"the LMI of eq. (28) is infeasible at lambda = {lam:g} ({margin}"
                      f"{'' if tried == ['full'] else ', M ' + ' or '.join(tried)}){worst if best <= 0 else ''}"
                      f"{unproved if best <= 0 and lam * 1.0 < eig_bound else ''}",
                      hint, check="lmi_margin")


def _formulation_meta(info: dict) -> dict:
    """Which problem gave M, for the artefact's meta."""
    out = {}
    if info:
        out["formulation"] = info["formulation"]
        if info["formulation"] == "scale_free":
            out.update(scale_free_objective=f"minimise kappa subject to I <= M <= kappa I and A_k^T M + M A_k + lambda M <= -{SCALE_FREE_MARGIN:g} kappa I; M then scaled to trace(M) = n",
                       scale_free_relative_margin=info["relative_margin"])
    return out


def _synthesise_feedback(model: Model, st, A_vertices: list[np.ndarray], meta: dict, poly: Polytope, scale: float = 1.0, explain: bool = True):
    """M, K and lambda for ``feedback: linear_gain`` (g constant), by the LMI in X = M^-1, Y = K X with the smallest
    gain (:func:`solve_lmi_feedback`).  ``A_vertices`` are divided by ``scale`` (rates too; K is unchanged)."""
    if st.method != "polytopic_lmi":
        raise SpecError("stabilisability.method", f"'{st.method}' with feedback linear_gain", "method polytopic_lmi (K is synthesised)")
    B = np.array(model.substitute(model.g), dtype=float) / scale
    weights = np.maximum(0.5 * (model.U[:, 1] - model.U[:, 0]), 1e-300)
    structure = "diagonal" if st.structure == "diagonal" else "full"   # auto: the feedback LMI is searched in full
    meta.update(solver="CLARABEL via cvxpy",
                normalisation=f"I <= M^-1 <= kappa I, kappa the first of {list(FEEDBACK_CONDITION)} that is feasible",
                objective=f"minimise mu subject to A X + X A^T + B Y + Y^T B^T + lambda (1 + {FEEDBACK_RATE_MARGIN:g}) X <= 0 at every vertex and "
                          "K_i X K_i^T <= mu w_i^2 (w_i: half the width of U_i); K = Y X^-1, M = X^-1: the smallest gain, "
                          "the largest region where no input clips",
                structure=structure)
    if st.decay_rate == "maximise":
        lam, found = largest_feedback_rate(A_vertices, B, structure, weights)
        if found is None:
            raise DesignError("stabilisability", "no feedback gain K makes A + B K incrementally stable with a positive decay rate "
                              f"at every vertex{_worst_vertex_text(poly, A_vertices, scale)}",
                              "a stabilisable pair (A, B) at every vertex", check="lmi_margin")
        M, K = found
        lam *= scale
        meta.update(bisection_rtol=BISECTION_RTOL, rate_cap=FEEDBACK_MAX_RATE * scale)
    else:
        lam = float(st.decay_rate)
        M, K, mu, status = solve_lmi_feedback(A_vertices, B, lam / scale, structure, weights)
        meta.update(status=status, weighted_gain=mu)
        if M is None and not explain:
            raise DesignError("stabilisability.decay_rate", f"no feedback gain makes eq. (28) feasible at lambda = {lam:g} on this polytope", "a finer one")
        if M is None:
            best, _ = largest_feedback_rate(A_vertices, B, structure, weights)
            hint = (f"decay_rate below {best * scale:.6g} (the largest the solver certifies with feedback), or 'maximise'" if best > 0 else
                    f"a stabilisable pair (A, B) at every vertex{_worst_vertex_text(poly, A_vertices, scale)}")
            raise DesignError("stabilisability.decay_rate", f"no feedback gain makes eq. (28) feasible at lambda = {lam:g}", hint, check="lmi_margin")
    return M, np.asarray(K, dtype=float), lam, meta


def _worst_vertex_text(poly: Polytope, A_vertices: list[np.ndarray], scale: float = 1.0) -> str:
    """'; at the vertex u = [..] of U, A has an eigenvalue with real part 0.5' (or at a corner of the ranges): the
    vertex whose A is least stable, which bounds every rate from above (lambda <= -2 Re eig(A))."""
    k = int(np.argmax([np.linalg.eigvals(A).real.max() for A in A_vertices]))
    re = float(np.linalg.eigvals(A_vertices[k]).real.max()) * scale
    if poly.kind == "affine in u":
        return f"; at the vertex {poly.labels[k]} of U, A(u) has an eigenvalue with real part {re:.4g}"
    ranges = poly.meta.get("ranges", poly.meta.get("term_ranges"))
    names = poly.meta.get("jacobian_entries", poly.meta.get("jacobian_terms", []))
    ranges_text = "; ".join(f"{n} in [{lo:.6g}, {hi:.6g}]" for n, (lo, hi) in zip(names, ranges)) if ranges is not None else ""
    return (f"; at the corner {poly.labels[k]} of the {'Jacobian ranges' if poly.kind == 'Jacobian entries' else 'ranges of the nonlinear terms'} "
            f"over state_box x U ({ranges_text}) df/dx has an eigenvalue with real part {re:.4g}")


def summarise(art: Artefact) -> dict:
    """Headline numbers for ``ashc summary``.

    Parameters
    ----------
    art : Artefact
        The stabilise stage's artefact.

    Returns
    -------
    dict
        lambda, M, K (None without a gain), lmi_margin, vertex_margins, M_min_eigenvalue, method, polytope, proof
        and A (entries as text).
    """
    v = art.values
    return {
        "lambda": float(v["lambda"]),
        "M": np.asarray(v["M"]).tolist(),
        "K": np.asarray(v["K"]).tolist() if "K" in v else None,
        "lmi_margin": float(v["lmi_margin"]),
        "vertex_margins": np.asarray(v["vertex_margins"]).tolist(),
        "M_min_eigenvalue": float(np.min(v["M_eigenvalues"])),
        "method": art.meta.get("method"),
        "polytope": art.meta.get("polytope"),
        "proof": art.meta.get("lmi_proof"),
        "route": art.meta.get("route"),
        "A": [str(e) for e in art.exprs["A"]],
    }


def headline(art: Artefact) -> str:
    """One progress line.

    Parameters
    ----------
    art : Artefact
        The stabilise stage's artefact.

    Returns
    -------
    str
        lambda and lmi_margin.
    """
    line = f"lambda = {art.values['lambda']:.6g}, lmi_margin = {art.values['lmi_margin']:.3g}"
    if "route" in art.meta:          # method given, or too many terms: the vertex argument or the norm-bound test
        proved = art.checks["lmi_margin"].evidence == proofs.PROVED
        line += (f" (method {art.meta.get('method', 'given')}, by {art.meta['route']}; "
                 + (f"proved margin {art.values['lmi_margin_proved']:.3g})" if proved else "sampled)"))
    return line
