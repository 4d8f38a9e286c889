"""Stage 1: asymptotic stabilisability by a quadratic incremental Lyapunov function (eq. egLMI).

With f(x, u) = A(u) x + b(u) and A affine in u (eq. ConvertSystemLinear), V(x, z) = (x - z)^T M (x - z)
(eq. egV) satisfies Theorem StabiliseLyap with k(z, x, u) = u when

    A(u)^T M + M A(u) <= -lambda M,   M > 0                                          (eq. egLMI)

for all u in U; since the left side is affine in u it suffices to impose it at the vertices of the box U.
The LMI is solved with cvxpy + Clarabel, maximising the margin t in A^T M + M A + lambda M <= t I under
the normalisation trace(M) = n, M >= 1e-3 I, and re-checked in numpy at the vertices and on a sweep of U.
That normalisation bounds trace(M) / lambda_min(M) by 4000, so a rate whose every M is more ill-conditioned
is refused by it; such a rate is then tried scale-free (:func:`solve_lmi_scale_free`: minimise the condition
number, I <= M <= kappa I), and accepted only if the numpy re-check of its margin, relative to ||M||, is
negative (:func:`certify_rate`, used by the fixed rate and by every step of the ``maximise`` bisection).
``maximise`` tries the eigenvalue bound on lambda first (often attained: then one solve decides), and narrows
its bracket from below by the rate each M found certifies and from above by the infeasibility the solver's
duals prove (:func:`largest_decay_rate`); the rate it reports is always one its M certifies.
M is searched in full, or diagonal (``stabilisability.structure``; ``auto`` tries a diagonal M first above
:data:`FULL_MAX_STATES` states, where the dense SDP grows like n^6: 13 s at n = 64, 300 s and 7.7 GiB at 128).

When f is not affine in x, the same LMI is imposed on a polytope that contains the Jacobian df/dx over
``concrete.state_box`` x U (:func:`jacobian_polytope`); the certificate then holds for solutions in that box.

``feedback: linear_gain`` (a plant that is not incrementally stable, with g(x) = B constant) synthesises K so
that k(z, x, u) = u + K (z - x) renders the pair incrementally stable: with X = M^-1 and Y = K X the
condition (A(u) + B K)^T M + M (A(u) + B K) <= -lambda M becomes the LMI
A X + X A^T + B Y + Y^T B^T + lambda X <= t I (t < 0); the interface then adds K (x - p(xi)) (eq. Interface).
"""

from __future__ import annotations

import itertools

import numpy as np
import sympy as sp

from .. import proofs
from ..artefacts import Artefact, Check
from ..contraction.feedback import FEEDBACK_CONDITION, FEEDBACK_MAX_RATE, FEEDBACK_RATE_MARGIN, _largest_feedback_rate, solve_lmi_feedback
from ..contraction.proof import prove_lmi
from ..contraction.terms import jacobian_polytope, jacobian_samples, refuse_jumps
from ..contraction.vertex import (BISECTION_RTOL, FULL_MAX_STATES, M_MIN_EIG, MARGIN_TOL, SCALE_FREE_MARGIN, certify_rate,  # noqa: F401
                                  infeasible_from, largest_decay_rate, largest_decay_rate_for, lmi_margins, lmi_scale, solve_lmi,
                                  structures, sweep, vertices)
from ..errors import DesignError, NumericalError, SpecError
from ..model import Model, jumps, sparse_jacobian, tidy

NAME = "stabilise"
UPSTREAM: tuple[str, ...] = ()


def affine_form(model: Model, J: sp.Matrix | None = None) -> tuple[sp.Matrix, sp.Matrix]:
    """Write f(x, u) = A(u) x + b(u) symbolically (eq. ConvertSystemLinear).

    ``J``, if given, is df/dx already computed (A is that Jacobian when f is affine in x).

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
    for (i, j), e in np.ndenumerate(np.array(A, dtype=object)):
        if e.free_symbols & xs:
            raise DesignError("concrete", f"f(x, u) is not affine in x: df{i + 1}/d{model.x[j]} = {e} depends on x",
                              "f(x, u) = A(u) x + b(u) for stabilisability.method polytopic_lmi or given")
        if not e.free_symbols.intersection(us):
            continue
        for a, b in itertools.product(us, us):
            second = sp.diff(e, a, b)
            if second != 0 and sp.simplify(second) != 0:   # simplify only what is not plainly zero
                raise DesignError("concrete", f"A(u) is not affine in u: entry ({i + 1}, {j + 1}) = {e}",
                                  "A(u) affine in u so that the LMI at the vertices of U covers all of U")
    b = tidy(sp.expand(model.f - A * model.x))
    for i, e in enumerate(b):
        if e.free_symbols & xs:
            raise DesignError("concrete", f"f(x, u) is not affine in x: f{i + 1} - (A x){i + 1} = {e} depends on x (a jump such as sign(x) has a zero "
                              "derivative almost everywhere but is not affine)",
                              "f(x, u) = A(u) x + b(u), or a concrete.state_box on which f is Lipschitz and C^1 almost everywhere")
    return tidy(A), b


def run(model: Model, upstream: dict[str, Artefact]) -> Artefact:
    """Certify stabilisability: M and lambda of eq. egLMI, with margins re-checked in numpy.

    Parameters
    ----------
    model : Model
        The spec's systems.
    upstream : dict
        Unused (the first stage).

    Returns
    -------
    Artefact
        Values M, lambda, vertex and sweep margins, lmi_margin; expressions A(u), b(u).

    Raises
    ------
    DesignError
        If f is not of the class the method needs, M is not positive definite, or the LMI is
        infeasible at the requested decay rate (the message gives the largest feasible one).
    NumericalError
        If the solver claims success but the numpy re-check fails.
    """
    st = model.spec.stabilisability
    meta: dict = {"method": st.method, "feedback": st.feedback}
    # Without a state box a plant not affine in x is refused by affine_form, with its reason.
    J = sparse_jacobian(model.f, model.x)
    # (a sign of a state has a Jacobian free of x almost everywhere, but f is not affine: its jump needs the box)
    affine = model.state_box is None or not (any(e.free_symbols & set(model.x) for e in J) or jumps(model.f, model.x))
    if affine:
        A_sym, b_sym = affine_form(model, J)
        A_num = model.numeric(A_sym, list(model.u))
        verts = vertices(model.U)
        A_vertices = [A_num(*vtx) for vtx in verts]
    else:
        if st.feedback == "linear_gain":
            raise SpecError("stabilisability.feedback", "'linear_gain' with f not affine in x", "feedback: identity (the Jacobian LMI certifies the plant itself)")
        refuse_jumps(model)
        A_sym, A_vertices, ranges, jmeta = jacobian_polytope(model, J)
        b_sym = sp.zeros(model.n, 1)
        verts = ranges
        meta.update(jmeta, condition="J(x, u)^T M + M J(x, u) <= -lambda M on state_box x U (Jacobian polytope)")
    K = np.zeros((model.m, model.n))
    # The LMI is solved on A / s, s the largest spectral radius (rates divided by s too; M and K are unchanged), so that
    # its tolerances are relative to the plant's own time scale: a plant in nanoseconds or in days is solved
    # as one in seconds.
    scale = lmi_scale(A_vertices)
    scaled = [A / scale for A in A_vertices]
    meta["lmi_scale"] = scale
    if not affine:
        meta["_ranges"] = ranges

    if st.feedback == "linear_gain":
        M, K, lam, meta = _synthesise_feedback(model, st, scaled, meta, scale)
    elif st.method == "given":
        M = np.array(st.M, dtype=float)
        if not np.allclose(M, M.T, rtol=0, atol=1e-12 * max(1.0, np.abs(M).max())):
            raise SpecError("stabilisability.M", "is not symmetric", "a symmetric positive definite matrix")
        if np.linalg.eigvalsh(M).min() <= 0:
            raise DesignError("stabilisability.M", f"is not positive definite (smallest eigenvalue {np.linalg.eigvalsh(M).min():.4g})", "M > 0", check="M_positive")
        lam_max = largest_decay_rate_for(A_vertices, M)
        lam = lam_max if st.decay_rate == "maximise" else float(st.decay_rate)
        meta.update(solver="none (M given; verified in numpy)")
    else:
        meta.update(solver="CLARABEL via cvxpy", normalisation=f"trace(M) = n (and M >= {M_MIN_EIG} I in the maximum-margin problem)",
                    objective="minimise t subject to A(u_k)^T M + M A(u_k) + lambda M <= t I at every vertex u_k",
                    margin_tol=MARGIN_TOL,
                    fallback=f"when that does not certify lambda: minimise kappa subject to I <= M <= kappa I and A(u_k)^T M + M A(u_k) + lambda M "
                             f"<= -{SCALE_FREE_MARGIN:g} kappa I, accepted when the numpy margin over ||M|| is below -{MARGIN_TOL:g}; M scaled to trace(M) = n")
        M, lam, meta = _search(scaled, st, structures(st.structure, model.n), meta, model, scale)

    meta.pop("_ranges", None)
    B_K = np.array(model.substitute(model.g), dtype=float) @ K if st.feedback == "linear_gain" else 0.0
    vertex_margins = lmi_margins([A + B_K for A in A_vertices], M, lam)
    if affine:
        sweep_u = sweep(model.U)
        A_sweep = np.broadcast_to(A_num(*sweep_u.T), (model.n, model.n, len(sweep_u)))   # one vectorised call
        sweep_margins = lmi_margins([A_sweep[:, :, k] + B_K for k in range(len(sweep_u))], M, lam)
    else:
        sweep_u = np.zeros((0, model.m))
        samples, where = jacobian_samples(model, A_sym)
        sweep_margins = lmi_margins(samples, M, lam)
        if sweep_margins.max() > 0:
            # A point of the box whose Jacobian breaks the LMI: the (sampled) ranges missed it, and no M found on
            # them certifies the plant. A counter-example, not a solver failure.
            k = int(np.argmax(sweep_margins))
            x_at, u_at = where[k, :model.n], where[k, model.n:]
            raise DesignError("stabilisability", f"eq. egLMI fails at x = {np.round(x_at, 6).tolist()}, u = {np.round(u_at, 6).tolist()} "
                              f"(margin {sweep_margins[k]:.3g} > 0 at lambda = {lam:.6g}): its Jacobian lies outside the sampled ranges "
                              f"({meta.get('range_method', '')})", "Jacobian ranges that ball arithmetic can enclose, or a smaller state_box",
                              check="lmi_margin")
    margin = float(max(vertex_margins.max(), sweep_margins.max()))
    eig_M = np.linalg.eigvalsh(M)
    meta.update(M_condition_number=float(eig_M.max() / eig_M.min()) if eig_M.min() > 0 else None)
    if (st.method == "polytopic_lmi" or st.feedback == "linear_gain") and margin > 0:
        raise NumericalError(NAME, f"Clarabel reported a solution but the numpy re-check finds margin {margin:.3g} > 0", "a certified M (margin <= 0)")
    if st.method == "given" and margin > 0:
        raise DesignError("stabilisability.M", f"does not satisfy eq. egLMI at lambda = {lam:g} (margin {margin:.4g} > 0)",
                          f"a decay_rate <= {largest_decay_rate_for(A_vertices, M):.6g}, the largest this M certifies", check="lmi_margin")

    proved_margin, proof = prove_lmi(model, A_sym, verts, affine, K, M, lam, ranges_proved=bool(meta.get("ranges_proved", False)))
    margin_evidence = proofs.PROVED if proved_margin <= 0 else proofs.SAMPLED
    M_lower = proofs.lambda_min_lower(M) if model.n <= proofs.MAX_PROOF_STATES else -np.inf
    meta.update(lmi_proof=proof if proved_margin <= 0 else f"not proved: {proof} (bound {proved_margin:.3g})")

    art = Artefact(stage=NAME, meta=meta)
    art.values.update({
        "lmi_margin_proved": proved_margin, "M_min_eigenvalue_proved": M_lower,
        "M": M, "K": K, "lambda": lam, "vertices": verts, "vertex_margins": vertex_margins, "sweep_u": sweep_u,
        "sweep_margins": sweep_margins, "lmi_margin": margin, "M_eigenvalues": eig_M,
        "A_vertices": np.stack(A_vertices), "relative_margin": margin / eig_M.max(),
    })
    art.exprs.update({"A": A_sym, "b": b_sym})
    if margin_evidence == proofs.PROVED:
        art.checks["lmi_margin"] = Check(proved_margin, True, "proved upper bound of the largest eigenvalue of A_cl^T M + M A_cl + lambda M, A_cl = A + B K "
                                         f"(K = 0 for identity feedback; <= 0: eq. egLMI holds): {proof}", proofs.PROVED)
    else:
        art.checks["lmi_margin"] = Check(margin, margin <= 0, "largest eigenvalue of A_cl(u)^T M + M A_cl(u) + lambda M over the vertices and a sweep of U, A_cl = A + B K "
                                         f"(K = 0 for identity feedback; <= 0: eq. egLMI holds); proof: {meta['lmi_proof']}")
    if M_lower > 0:
        art.checks["M_positive"] = Check(M_lower, True, "proved lower bound of the smallest eigenvalue of M (> 0; arb Cholesky)", proofs.PROVED)
    else:
        art.checks["M_positive"] = Check(float(eig_M.min()), bool(eig_M.min() > 0), "smallest eigenvalue of M (> 0; numpy)")
    return art


def _search(A_vertices: list[np.ndarray], st, tries: list[str], meta: dict, model: Model, scale: float = 1.0) -> tuple[np.ndarray, float, dict]:
    """M and lambda of eq. egLMI (identity feedback), trying each structure of M in turn.

    ``A_vertices`` are divided by ``scale`` (so are the rates inside; the lambda returned is in the plant's units).
    A later structure is tried only when the earlier one finds no M (at the requested rate, or with any
    positive rate for ``maximise``); ``meta["structure"]`` records the one used and ``meta["tried"]`` all.
    """
    tried = []
    for structure in tries:
        tried.append(structure)
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
    worst = _worst_vertex_text(model, A_vertices, meta, scale)
    other = ("feedback: linear_gain (g constant, f affine in x) to synthesise a stabilising K" if "jacobian_entries" not in meta
             else "a smaller concrete.state_box (the Jacobian ranges are taken over all of it, each entry independently)")
    # The eigenvalues bound every rate from above (Re eig(A_k) <= -lambda / 2); below that bound the solver's
    # failure to find an M is not a proof that none exists (an M may have to be very ill-conditioned).
    eig_bound = min(-2.0 * float(np.linalg.eigvals(A).real.max()) for A in A_vertices) * scale
    unproved = (f"; the eigenvalues allow rates up to {eig_bound:.6g}, so an M may exist that the solver could not reach "
                f"(very ill-conditioned): a given M (method: given) is verified exactly") if eig_bound > 0 else ""
    if st.decay_rate == "maximise":
        what = "no M certifies any decay rate lambda > 0" if eig_bound <= 0 else "the solver found no M certifying a decay rate lambda > 0"
        raise DesignError("stabilisability", f"{what} (eq. egLMI){worst}{unproved}",
                          f"a plant that is incrementally stable on the set, or {other}", check="lmi_margin")
    best, _ = largest_decay_rate(A_vertices, structure=tries[-1])
    hint = (f"decay_rate below {best * scale:.6g} (the largest the solver certifies), or 'maximise'" if best > 0
            else f"a plant that is incrementally stable on the set, or {other}")
    margin = f"best margin {t * scale:.3g}" if np.isfinite(t) else "no solution"
    raise DesignError("stabilisability.decay_rate", f"the LMI of eq. egLMI is infeasible at lambda = {lam:g} ({margin}"
                      f"{'' if tried == ['full'] else ', M ' + ' or '.join(tried)}){worst if best <= 0 else ''}"
                      f"{unproved if best <= 0 and lam * 1.0 < eig_bound else ''}",
                      hint, check="lmi_margin")


def _formulation_meta(info: dict) -> dict:
    """Which problem gave M, for the artefact's meta."""
    out = {}
    if info:
        out["formulation"] = info["formulation"]
        if info["formulation"] == "scale_free":
            out.update(scale_free_objective=f"minimise kappa subject to I <= M <= kappa I and A(u_k)^T M + M A(u_k) + lambda M <= -{SCALE_FREE_MARGIN:g} kappa I; M then scaled to trace(M) = n",
                       scale_free_relative_margin=info["relative_margin"])
    return out


def _synthesise_feedback(model: Model, st, A_vertices: list[np.ndarray], meta: dict, scale: float = 1.0):
    """M, K and lambda for ``feedback: linear_gain`` (g constant), by the LMI in X = M^-1, Y = K X with the smallest
    gain (:func:`solve_lmi_feedback`).  ``A_vertices`` are divided by ``scale`` (rates too; K is unchanged)."""
    if st.method != "polytopic_lmi":
        raise SpecError("stabilisability.method", f"'{st.method}' with feedback linear_gain", "method polytopic_lmi (K is synthesised)")
    if any(e.free_symbols & set(model.x) for e in model.g):
        raise DesignError("concrete.g", "feedback linear_gain needs a constant input matrix g", "g independent of x, or feedback identity")
    B = np.array(model.substitute(model.g), dtype=float) / scale
    weights = np.maximum(0.5 * (model.U[:, 1] - model.U[:, 0]), 1e-300)
    structure = "diagonal" if st.structure == "diagonal" else "full"   # auto: the feedback LMI is searched in full
    meta.update(solver="CLARABEL via cvxpy",
                normalisation="I <= M^-1 <= kappa I, kappa the first of %s that is feasible" % list(FEEDBACK_CONDITION),
                objective="minimise mu subject to A X + X A^T + B Y + Y^T B^T + lambda (1 + %g) X <= 0 at every vertex and "
                          "K_i X K_i^T <= mu w_i^2 (w_i: half the width of U_i); K = Y X^-1, M = X^-1: the smallest gain, "
                          "the largest region where no input clips" % FEEDBACK_RATE_MARGIN,
                structure=structure)
    if st.decay_rate == "maximise":
        lam, found = _largest_feedback_rate(A_vertices, B, structure, weights)
        if found is None:
            raise DesignError("stabilisability", "no feedback gain K makes A(u) + B K incrementally stable with a positive decay rate "
                              f"at every vertex{_worst_vertex_text(model, A_vertices, meta, scale)}",
                              "a stabilisable pair (A(u), B) at every vertex of U", check="lmi_margin")
        M, K = found
        lam *= scale
        meta.update(bisection_rtol=BISECTION_RTOL, rate_cap=FEEDBACK_MAX_RATE * scale)
    else:
        lam = float(st.decay_rate)
        M, K, mu, status = solve_lmi_feedback(A_vertices, B, lam / scale, structure, weights)
        meta.update(status=status, weighted_gain=mu)
        if M is None:
            best, _ = _largest_feedback_rate(A_vertices, B, structure, weights)
            hint = (f"decay_rate below {best * scale:.6g} (the largest the solver certifies with feedback), or 'maximise'" if best > 0 else
                    f"a stabilisable pair (A(u), B) at every vertex of U{_worst_vertex_text(model, A_vertices, meta, scale)}")
            raise DesignError("stabilisability.decay_rate", f"no feedback gain makes eq. egLMI feasible at lambda = {lam:g}", hint, check="lmi_margin")
    return M, np.asarray(K, dtype=float), lam, meta


def _worst_vertex_text(model: Model, A_vertices: list[np.ndarray], meta: dict, scale: float = 1.0) -> str:
    """'; at u = [..] A has an eigenvalue with real part 0.5' (or at the corner of the Jacobian ranges df2/dx1 = ..):
    the vertex whose A is least stable, which bounds every rate from above (lambda <= -2 Re eig(A))."""
    k = int(np.argmax([np.linalg.eigvals(A).real.max() for A in A_vertices]))
    re = float(np.linalg.eigvals(A_vertices[k]).real.max()) * scale
    if "jacobian_entries" in meta:
        ranges = meta.get("_ranges")
        names = meta["jacobian_entries"]
        corner = list(itertools.product(*[tuple(r) for r in ranges]))[k] if ranges is not None else ()
        where = ", ".join(f"{n} = {v:.6g}" for n, v in zip(names, corner))
        ranges_text = "; ".join(f"{n} in [{lo:.6g}, {hi:.6g}]" for n, (lo, hi) in zip(names, ranges)) if ranges is not None else ""
        return (f"; at the corner {where} of the Jacobian ranges over state_box x U ({ranges_text}) df/dx has an eigenvalue "
                f"with real part {re:.4g}")
    verts = vertices(model.U)
    return f"; at the vertex u = {np.round(verts[k], 6).tolist()} of U, A(u) has an eigenvalue with real part {re:.4g}"


def summarise(art: Artefact) -> dict:
    """Headline numbers for ``ashc summary``."""
    v = art.values
    return {
        "lambda": float(v["lambda"]),
        "M": np.asarray(v["M"]).tolist(),
        "K": np.asarray(v["K"]).tolist() if "K" in v else None,
        "lmi_margin": float(v["lmi_margin"]),
        "vertex_margins": np.asarray(v["vertex_margins"]).tolist(),
        "M_min_eigenvalue": float(np.min(v["M_eigenvalues"])),
        "method": art.meta.get("method"),
        "A": [str(e) for e in art.exprs["A"]],
    }


def headline(art: Artefact) -> str:
    """One progress line."""
    return f"lambda = {art.values['lambda']:.6g}, lmi_margin = {art.values['lmi_margin']:.3g}"
