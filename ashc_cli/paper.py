"""The paper's numbering and where the code implements it.

:data:`LABELS`: its LaTeX labels as the published paper numbers them, and :func:`cite`, which rewrites text that
quotes a label ("eq. SimuFuncCondi1" -> "eq. (6)").  The code cites the numbers (a test keeps labels out of it);
docs/theory.md keeps both.  The table is docs/labels.json (counted from the paper's source, see docs/theory.md); a
test keeps the two equal.

:data:`EQUATIONS`: every numbered equation, what it says, and the functions that implement it (their docstrings
cite it: a test holds each home to its citation) or, where no function does, where it lives instead.
docs/theory.md's table "Where each equation lives" is :func:`equation_table` (``make docs`` writes it; a test keeps
them equal).
"""

from __future__ import annotations

import re
from dataclasses import dataclass

__all__ = ["LABELS", "cite", "Equation", "EQUATIONS", "equation_table"]

#: label -> how the paper numbers it ("eq. (6)", "Theorem 2", "Fig. 5", "Section III-A", ...).
LABELS: dict[str, str] = {
    'intro': 'Section I',
    'Hierarchical_Structure': 'Fig. 1',
    'prelimiaries': 'Section II',
    'ControlSystem': 'Definition 1',
    'ConcreteSystem': 'eq. (1)',
    'AbstractSystem': 'eq. (2)',
    'stabilisab': 'Definition 2',
    'funcff': 'eq. (3)',
    'trajConverge': 'eq. (4)',
    'StabiliseLyap': 'Theorem 1',
    'stabilisableV': 'eq. (5)',
    'stabilisableCond1': 'eq. (5a)',
    'stabilisableCond2': 'eq. (5b)',
    'formulate': 'Section III',
    'BODintro': 'Section III-A',
    'simuFunction': 'Definition 3',
    'SimuFuncCondi1': 'eq. (6)',
    'SimuFuncCondi2': 'eq. (7)',
    'ErrorBound': 'Theorem 2',
    'TrackConst': 'eq. (9)',
    'SimuLocalRequire': 'eq. (10)',
    'mRelat': 'Definition 4',
    'mRelatDiff': 'eq. (11a)',
    'mRelatOut': 'eq. (11b)',
    'mRelatOutMatch': 'Theorem 3',
    'ASHC': 'Problem 1',
    'solution': 'Section IV',
    'abstractAffine': 'eq. (12)',
    'concreteAffine': 'eq. (13)',
    'BODdesign': 'Section IV-A',
    'outputLipstchiz': 'Assumption 1',
    'SimuDesign': 'Theorem 4',
    'SimuDesignCond1': 'eq. (14a)',
    'SimuDesignCond2': 'eq. (14b)',
    'Interface': 'eq. (15)',
    'SimuResBound': 'eq. (16)',
    'condB': 'Proposition 1',
    'bounddVdx': 'eq. (17)',
    'SimuResBoundYoung': 'eq. (18)',
    'uMinBound': 'eq. (20)',
    'LinearCompare': 'Remark 3',
    'SimuNotAffine': 'Remark 4',
    'solvePDE': 'Remark 5',
    'mRelateDesign': 'Section IV-B',
    'mRelatePDE': 'Lemma 1',
    'mRelatSuffi': 'eq. (21)',
    'mRelatSuffiDiff': 'eq. (21a)',
    'mRelatSuffiIn': 'eq. (21b)',
    'mRelatSuffiOut': 'eq. (21c)',
    'mRelateLink': 'eq. (22)',
    'mRelateInterconnect': 'Fig. 2',
    'mRelateDelta': 'Theorem 5',
    'Flow_Chart': 'Fig. 3',
    'RelateMM': 'Remark 6',
    'steps': 'Section IV-C',
    'mCondi': 'Theorem 6',
    'mRelationImP': 'eq. (23)',
    'mRelateGeo': 'Corollary 1',
    'GeoCondi': 'eq. (24)',
    'example': 'Section V',
    'Converter_Circuit': 'Fig. 4',
    'ConverterAveMod': 'eq. (25)',
    'ConvertSystem': 'eq. (26)',
    'ConvertSystemLinear': 'eq. (27)',
    'parameter': 'Table I',
    'egLMI': 'eq. (28)',
    'egM': 'eq. (29)',
    'egV': 'eq. (30)',
    'egSimuDesign': 'eq. (31)',
    'egKappa': 'eq. (32)',
    'mEquation': 'eq. (33)',
    'egm': 'eq. (34)',
    'kappa_xi': 'Fig. 5',
    'egSimuFunc': 'eq. (35)',
    'egConditionB': 'eq. (36)',
    'iota': 'eq. (37)',
    'delta_Compare': 'Fig. 6',
    'egErrorBound': 'eq. (38)',
    'egDelta': 'eq. (39)',
    'egMrelateLink': 'eq. (40)',
    'egAbstract': 'eq. (41)',
    'egInterface': 'eq. (42)',
    'egqLS': 'eq. (43)',
    'egInterfaceSat': 'eq. (44)',
    'Example_BoundedIn': 'Fig. 7',
    'Example_BoundedOut': 'Fig. 8',
    'Example_mRelationIn': 'Fig. 9',
    'Example_mRelationOut': 'Fig. 10',
    'concl': 'Section VI',
    'sec:intro': 'Section I',
    'fig:Hierarchical_Structure': 'Fig. 1',
    'sec:prelimiaries': 'Section II',
    'def:ControlSystem': 'Definition 1',
    'equ:ConcreteSystem': 'eq. (1)',
    'equ:AbstractSystem': 'eq. (2)',
    'def:stabilisab': 'Definition 2',
    'equ:funcff': 'eq. (3)',
    'equ:trajConverge': 'eq. (4)',
    'thm:StabiliseLyap': 'Theorem 1',
    'equ:stabilisableV': 'eq. (5)',
    'equ:stabilisableCond1': 'eq. (5a)',
    'equ:stabilisableCond2': 'eq. (5b)',
    'sec:formulate': 'Section III',
    'subsec:BODintro': 'Section III-A',
    'def:simuFunction': 'Definition 3',
    'equ:SimuFuncCondi1': 'eq. (6)',
    'equ:SimuFuncCondi2': 'eq. (7)',
    'thm:ErrorBound': 'Theorem 2',
    'equ:ErrorBound': 'eq. (8)',
    'equ:TrackConst': 'eq. (9)',
    'equ:SimuLocalRequire': 'eq. (10)',
    'def:mRelat': 'Definition 4',
    'equ:mRelat': 'eq. (11)',
    'equ:mRelatDiff': 'eq. (11a)',
    'equ:mRelatOut': 'eq. (11b)',
    'thm:mRelatOutMatch': 'Theorem 3',
    'prob:ASHC': 'Problem 1',
    'sec:solution': 'Section IV',
    'equ:abstractAffine': 'eq. (12)',
    'equ:concreteAffine': 'eq. (13)',
    'subsec:BODdesign': 'Section IV-A',
    'asmp:outputLipstchiz': 'Assumption 1',
    'thm:SimuDesign': 'Theorem 4',
    'equ:SimuDesign': 'eq. (14)',
    'equ:SimuDesignCond1': 'eq. (14a)',
    'equ:SimuDesignCond2': 'eq. (14b)',
    'equ:Interface': 'eq. (15)',
    'equ:SimuResBound': 'eq. (16)',
    'prop:condB': 'Proposition 1',
    'equ:bounddVdx': 'eq. (17)',
    'equ:SimuResBoundYoung': 'eq. (18)',
    'equ:uMinBound': 'eq. (20)',
    'rmk:LinearCompare': 'Remark 3',
    'rmk:SimuNotAffine': 'Remark 4',
    'rmk:solvePDE': 'Remark 5',
    'subsec:mRelateDesign': 'Section IV-B',
    'lem:mRelatePDE': 'Lemma 1',
    'equ:mRelatSuffi': 'eq. (21)',
    'equ:mRelatSuffiDiff': 'eq. (21a)',
    'equ:mRelatSuffiIn': 'eq. (21b)',
    'equ:mRelatSuffiOut': 'eq. (21c)',
    'equ:mRelateLink': 'eq. (22)',
    'fig:mRelateInterconnect': 'Fig. 2',
    'thm:mRelateDelta': 'Theorem 5',
    'fig:Flow_Chart': 'Fig. 3',
    'rmk:RelateMM': 'Remark 6',
    'subsec:steps': 'Section IV-C',
    'thm:mCondi': 'Theorem 6',
    'equ:mRelationImP': 'eq. (23)',
    'corol:mRelateGeo': 'Corollary 1',
    'equ:GeoCondi': 'eq. (24)',
    'sec:example': 'Section V',
    'fig:Converter_Circuit': 'Fig. 4',
    'equ:ConverterAveMod': 'eq. (25)',
    'equ:ConvertSystem': 'eq. (26)',
    'equ:ConvertSystemLinear': 'eq. (27)',
    'tab:parameter': 'Table I',
    'equ:egLMI': 'eq. (28)',
    'equ:egM': 'eq. (29)',
    'equ:egV': 'eq. (30)',
    'equ:egSimuDesign': 'eq. (31)',
    'equ:egKappa': 'eq. (32)',
    'equ:mEquation': 'eq. (33)',
    'equ:egm': 'eq. (34)',
    'fig:kappa_xi': 'Fig. 5',
    'equ:egSimuFunc': 'eq. (35)',
    'equ:egConditionB': 'eq. (36)',
    'equ:iota': 'eq. (37)',
    'fig:delta_Compare': 'Fig. 6',
    'equ:egErrorBound': 'eq. (38)',
    'equ:egDelta': 'eq. (39)',
    'equ:egMrelateLink': 'eq. (40)',
    'equ:egAbstract': 'eq. (41)',
    'equ:egInterface': 'eq. (42)',
    'equ:egqLS': 'eq. (43)',
    'equ:egInterfaceSat': 'eq. (44)',
    'fig:Example_BoundedIn': 'Fig. 7',
    'fig:Example_BoundedOut': 'Fig. 8',
    'fig:Example_mRelationIn': 'Fig. 9',
    'fig:Example_mRelationOut': 'Fig. 10',
    'sec:concl': 'Section VI',
}

_KINDS = r"eqs?\.|Thm\.|Theorem|Prop\.|Proposition|Cor\.|Corollary|Def\.|Definition|Assumption|Lemma|Remarks?|Figs?\.|Section"
_ITEM = r"(?!(?:eqs?|Thm|Prop|Cor|Def|Figs?)\.)[A-Za-z_][A-Za-z0-9_]*(?:/[A-Za-z0-9_]+)?"
_CITATION = re.compile(rf"\b({_KINDS})\s+({_ITEM}(?:(?:, | and ){_ITEM})*)")
_PLURAL = {"eq.": "eqs.", "Fig.": "Figs."}


def _expand(item: str) -> list[str]:
    """"Example_BoundedIn/Out" -> the labels Example_BoundedIn and Example_BoundedOut (when both exist)."""
    if "/" not in item:
        return [item]
    head, tail = item.split("/", 1)
    for cut in range(len(head) - 1, 0, -1):
        if head[:cut] + tail in LABELS:
            return [head, head[:cut] + tail]
    return [item]


def cite(text: str) -> str:
    """``text`` with every citation of known labels written as the paper numbers it.

    "eq. SimuFuncCondi1" -> "eq. (6)"; "Thm. mCondi (ii), Cor. mRelateGeo" -> "Theorem 6 (ii), Corollary 1";
    "eqs. mRelatSuffiDiff, mRelatSuffiIn" -> "eqs. (21a), (21b)".  Words after the labels ("step 1") and
    unknown names are left as they are.

    Parameters
    ----------
    text : str

    Returns
    -------
    str
    """

    def replace(match: re.Match) -> str:
        items = re.split(r"(, | and )", match.group(2))
        names, rest = [], ""
        for k in range(0, len(items), 2):
            expanded = _expand(items[k])
            if all(e in LABELS for e in expanded):
                names.extend(expanded)
            else:
                rest = "".join(items[k - 1:]) if k else "".join(items)
                break
        if not names:
            return match.group(0)
        values = [LABELS[n] for n in names]
        if len(values) == 1:
            out = values[0]
        else:
            kind = values[0].split(" ", 1)[0]
            numbers = [v.split(" ", 1)[1] if v.split(" ", 1)[0] == kind else v for v in values]
            out = f"{_PLURAL.get(kind, kind + 's')} {', '.join(numbers)}"
        return out + rest

    return _CITATION.sub(replace, text)


@dataclass(frozen=True)
class Equation:
    """One numbered equation of the paper and its home in the code.

    Parameters
    ----------
    number : str
        As the paper numbers it: "eq. (15)".
    says : str
        What it says, in one line of plain text.
    code : tuple of str
        The functions or classes that implement it, by qualified name (their docstrings cite ``number``).
    elsewhere : str
        Where it lives when no function implements it (a definition, a step of a proof, the example's data).
    """

    number: str
    says: str
    code: tuple[str, ...] = ()
    elsewhere: str = ""


_C = "ashc_cli."
#: Every equation the paper numbers, in order (one row each; the pairs (5), (11), (14), (21) name their parts).
EQUATIONS: tuple[Equation, ...] = (
    Equation("eq. (1)", "the concrete system x' = f(x, u), y = h(x)", (_C + "problem.spec.Concrete", _C + "problem.model.Model")),
    Equation("eq. (2)", "the abstract system xi' = phi(xi, v), psi = kappa(xi)", (_C + "problem.spec.Abstract", _C + "problem.model.Model")),
    Equation("eq. (3)", "the plant and its copy under the feedback k: (f(x, u), f(z, k(z, x, u)))",
             (_C + "design.contraction.feedback.solve_lmi_feedback",)),
    Equation("eq. (4)", "asymptotic stabilisability: ||x(t) - z(t)|| <= beta(||x0 - z0||, t)",
             elsewhere="a property (Definition 2), certified through Theorem 1's conditions (5a), (5b), never checked directly"),
    Equation("eq. (5)", "Theorem 1's Lyapunov conditions on V(x, z)", elsewhere="the pair (5a), (5b)"),
    Equation("eq. (5a)", "alpha_lo(||x - z||) <= V(x, z) <= alpha_hi(||x - z||)",
             elsewhere="holds for the quadratic V of eq. (30) once M > 0, which the stabilise stage checks (row 'M positive definite')"),
    Equation("eq. (5b)", "V decreases along (3): dV/dx f(x, u) + dV/dz f(z, k) <= -alpha(||x - z||)",
             (_C + "design.contraction.vertex.solve_lmi", _C + "design.contraction.proof.prove_lmi")),
    Equation("eq. (6)", "W(xi, x) >= alpha_h(||kappa(xi) - h(x)||)", (_C + "design.stages.bound.alpha_h_linear", _C + "design.bound_proofs.prove_alpha_h")),
    Equation("eq. (7)", "the decrease of the simulation function: dW <= -eta(W) + gamma(||v||)", (_C + "design.stages.bound.run",)),
    Equation("eq. (8)", "Theorem 2's bound on ||psi - y|| from W0 and ||v||_inf",
             (_C + "design.stages.bound.error_bound_gain", _C + "closedloop.plan.guaranteed_plan")),
    Equation("eq. (9)", "a tracking tolerance: the bound of (8) at most epsilon", (_C + "closedloop.plan.guaranteed_plan",)),
    Equation("eq. (10)", "V covers Y: every psi in Y is kappa(xi) for some xi in V", (_C + "design.stages.inverse.run",)),
    Equation("eq. (11)", "the m-relation", elsewhere="the pair (11a), (11b)"),
    Equation("eq. (11a)", "dm/dx f(x, u) = phi(m(x), v)", (_C + "design.stages.delta.run",)),
    Equation("eq. (11b)", "h(x) = kappa(m(x))", (_C + "design.stages.inverse.run",)),
    Equation("eq. (12)", "an input-affine abstraction: phi(xi, v) = phi_bar(xi) + delta(xi) v", (_C + "problem.spec.Abstract",)),
    Equation("eq. (13)", "an input-affine plant: f(x, u) = f_bar(x) + g(x) u", (_C + "problem.model.Model.affine",)),
    Equation("eq. (14)", "Theorem 4's design conditions", elsewhere="the pair (14a), (14b)"),
    Equation("eq. (14a)", "the invariance PDE dp/dxi phi_bar(xi) = f_bar(p(xi)) + g(p(xi)) l(xi)",
             (_C + "design.stages.manifold.run", _C + "design.manifold_numeric.solve_collocation")),
    Equation("eq. (14b)", "kappa(xi) = h(p(xi))", (_C + "design.stages.kappa.run",)),
    Equation("eq. (15)", "the interface u_w = k(x, p(xi), l(xi)) + u*(xi, x, v)", (_C + "closedloop.interface.apply", _C + "closedloop.interface.feedback_of")),
    Equation("eq. (16)", "condition (B): the cross term of dW bounded by alpha*(||p(xi) - x||) + gamma(||v||)", (_C + "design.stages.bound.run",)),
    Equation("eq. (17)", "||dV/dx||^2 <= alpha_hat(||x - z||)",
             elsewhere="holds for every quadratic V (eq. (30)): ||dV/dx||^2 = 4 e^T M^2 e; nothing to compute"),
    Equation("eq. (18)", "Young's inequality on the cross term of (16)",
             elsewhere="a step of Proposition 1's proof; its epsilon is the bound stage's epsilon = lambda / 2"),
    Equation("eq. (20)", "u* = q(xi, x) v", (_C + "closedloop.interface.q_of",)),
    Equation("eq. (21)", "Lemma 1's sufficient conditions for the m-relation", elsewhere="the parts (21a), (21b), (21c)"),
    Equation("eq. (21a)", "dm/dx f_bar(x) = phi_bar(m(x)) + delta(m(x)) b(x)", (_C + "design.stages.delta.run",)),
    Equation("eq. (21b)", "dm/dx g(x) = delta(m(x)) c(x)", (_C + "design.stages.delta.run",)),
    Equation("eq. (21c)", "h(x) = kappa(m(x)) on X_y", (_C + "design.stages.inverse.run",)),
    Equation("eq. (22)", "the m-relation's link v = b(x) + c(x) u", (_C + "closedloop.tracking_core.link_loop", _C + "closedloop.compiled.MRelationLoop")),
    Equation("eq. (23)", "condition (ii): h(X_y outside Im(p)) inside h(Im(p))", (_C + "design.stages.inverse.run",)),
    Equation("eq. (24)", "Corollary 1: x - p(m(x)) in Ker(h)", (_C + "design.stages.inverse.choose_left_inverse",)),
    Equation("eq. (25)", "the Cuk converter's averaged model", elsewhere="specs/cuk_converter.yaml (concrete.f_bar, concrete.g)"),
    Equation("eq. (26)", "the converter as x' = f_bar(x) + g(x) u, y = C x", elsewhere="specs/cuk_converter.yaml"),
    Equation("eq. (27)", "f(x, u) = A(u) x + b", (_C + "design.stages.stabilise.affine_form",)),
    Equation("eq. (28)", "the LMI A(u)^T M + M A(u) <= -lambda M, M > 0, at the vertices of U",
             (_C + "design.contraction.vertex.solve_lmi", _C + "design.contraction.proof.prove_lmi")),
    Equation("eq. (29)", "the paper's M for the converter", elsewhere="specs/cuk_converter_paper_M.yaml (stabilisability.method: given) verifies it"),
    Equation("eq. (30)", "V(x, z) = (x - z)^T M (x - z)", (_C + "design.stages.stabilise.run",)),
    Equation("eq. (31)", "the converter's phi_bar = 0 and p(xi)", elsewhere="the manifold stage solves (14a) for specs/cuk_converter.yaml"),
    Equation("eq. (32)", "the converter's kappa(xi)", elsewhere="the kappa stage composes (14b) for specs/cuk_converter.yaml"),
    Equation("eq. (33)", "the converter's quadratic for m", elsewhere="the inverse stage solves it for specs/cuk_converter.yaml (row 'm real on Y')"),
    Equation("eq. (34)", "the converter's left inverse m(x)", elsewhere="the inverse stage picks the branch with m(p(xi)) = xi for specs/cuk_converter.yaml"),
    Equation("eq. (35)", "W(xi, x) = (p(xi) - x)^T M (p(xi) - x)", (_C + "design.upstream.tracking_start", _C + "design.stages.bound.run")),
    Equation("eq. (36)", "condition (B) for the quadratic W, with Young's epsilon", (_C + "design.stages.bound.run",)),
    Equation("eq. (37)", "vartheta = sqrt(M) (dp/dxi delta - g q)", (_C + "design.stages.bound.theta_norms", _C + "closedloop.interface.residual")),
    Equation("eq. (38)", "G = sqrt(2 / (alpha_h (lambda - eps) eps)) d-bar", (_C + "design.stages.bound.error_bound_gain",)),
    Equation("eq. (39)", "the converter's delta(xi)", elsewhere="specs/cuk_converter.yaml (abstract.delta)"),
    Equation("eq. (40)", "the converter's link b(x), c(x) = 0", elsewhere="the delta stage builds it for specs/cuk_converter.yaml (errata item 3)"),
    Equation("eq. (41)", "the converter's abstraction", elsewhere="specs/cuk_converter.yaml (abstract)"),
    Equation("eq. (42)", "the converter's interface u_w = xi + q v (eq. (15) with l(xi) = xi)", (_C + "closedloop.interface.apply",)),
    Equation("eq. (43)", "the least-squares q = (g^T M g)^-1 g^T M dp/dxi delta", (_C + "closedloop.interface.q_of", _C + "numerics.linalg.least_squares_q")),
    Equation("eq. (44)", "the saturated interface u = sat(xi + q v)", (_C + "closedloop.interface.saturate", _C + "closedloop.interface.apply_saturation")),
)


def equation_table() -> str:
    """docs/theory.md's table "Where each equation lives", in Markdown, from :data:`EQUATIONS`.

    Returns
    -------
    str
        The table's lines, a header and one row per equation.
    """
    rows = ["| equation | says | implemented by |", "| --- | --- | --- |"]
    for eq in EQUATIONS:
        where = ", ".join(f"`{name.removeprefix(_C)}`" for name in eq.code) if eq.code else f"({eq.elsewhere})"
        rows.append(f"| {eq.number} | {eq.says} | {where} |".replace("||", "\\|\\|"))
    return "\n".join(rows) + "\n"
