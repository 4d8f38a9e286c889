"""The verdict on Problem 1 (Nonlinear ASHC): one row per condition of the paper, each with its number.

Problem 1 asks for (1) a local simulation function on some V satisfying eq. (10) and (2) an
m-relation on Y.  By Theorem 4 with Proposition 1, (1) holds when Assumption 1, the
stabilisability certificate, the invariance PDE, l(V) in U, eq. (10) and condition (B) hold; by
Lemma 1 with Theorems 5 and 6, (2) holds when p is injective on V, conditions (i)
and (ii), m is real on Y, delta has full row rank and b, c solve eqs. (21a), (21b).  Each row reads
a check a design stage stored; :func:`verdict` is a pure function of the artefacts (and of the error that
stopped the design, if one did).

The verdict has three values.  ``proved``: every row passes and every row is *proved* (interval arithmetic,
sympy identities, ball-matrix Cholesky): each number that enters Problem 1, the gain G and the certified region
holds on the whole set it is about.  ``sampled``: every row passes, but some only on samples (a grid, random
points); the design is then not certified, and the line names those rows.  ``fails``: some row fails or was
not reached.  A certification tool may say "I could not prove this"; it never says "proved" on samples.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass

import numpy as np

from ashc_cli.design.artefacts import Artefact
from ashc_cli.errors import AshcError
from ashc_cli.paper import cite

__all__ = ["Row", "ROWS", "Verdict", "verdict", "PROVED", "SAMPLED", "FAILS", "GUARANTEE_CHECKS", "contradictions"]

#: The three verdicts (``ashc check --json`` key ``verdict``).
PROVED, SAMPLED, FAILS = "proved", "sampled", "fails"


@dataclass(frozen=True)
class Row:
    """One condition of Problem 1 and how it came out."""

    condition: str
    reference: str
    requirement: str      # "simulation function" or "m-relation"
    status: str           # "pass", "fail" or "not reached"
    value: float | None
    detail: str
    evidence: str = "-"   # "proved", "sampled" or "simulated" (how the stage established it); "-" when not reached

    def as_dict(self) -> dict:
        return asdict(self)


#: (condition, paper reference, requirement of Problem 1, stage, stored check name)
ROWS = (
    ("Assumption 1: h Lipschitz", "Assumption 1", "simulation function", "bound", "h_lipschitz"),
    ("alpha_h > 0 (W bounds the output error)", "eq. (6)", "simulation function", "bound", "alpha_h"),
    ("stabilisability certificate (LMI margin)", "eq. (28), Theorem 1", "simulation function", "stabilise", "lmi_margin"),
    ("M positive definite", "eq. (30)", "simulation function", "stabilise", "M_positive"),
    ("invariance PDE residual", "eq. (14a)", "simulation function", "manifold", "pde_residual"),
    ("l maps V into U", "Theorem 4", "simulation function", "manifold", "l_in_U"),
    ("V covers Y", "eq. (10)", "simulation function", "inverse", "V_covers_Y"),
    ("condition (B)", "Proposition 1", "simulation function", "bound", "condition_B"),
    ("region where the bound is certified", "Theorem 2, Definition 3", "simulation function", "bound", "certified_region"),
    ("p injective on V (left inverse)", "Theorem 6, step 1", "m-relation", "inverse", "left_inverse"),
    ("condition (i)", "Theorem 6 (i)", "m-relation", "inverse", "condition_i"),
    ("condition (ii)", "Theorem 6 (ii), Corollary 1", "m-relation", "inverse", "condition_ii"),
    ("m real on Y", "eq. (33)", "m-relation", "inverse", "m_real_on_Y"),
    ("delta full row rank on V", "Theorem 5", "m-relation", "delta", "rank_delta"),
    ("b, c solve the m-relation PDEs", "eqs. (21a), (21b)", "m-relation", "delta", "m_relation_link"),
)


#: Rows that exist only for some plants: the disturbance's term of the bound (``concrete.disturbances``).
OPTIONAL_ROWS = (
    ("disturbance term bounded", "Proposition 1", "simulation function", "bound", "disturbance_term"),
)


@dataclass(frozen=True)
class Verdict:
    """Problem 1's verdict: ``kind`` is ``proved``, ``sampled`` or ``fails``, with the rows it rests on."""

    kind: str
    rows: tuple[Row, ...]

    @property
    def solved(self) -> bool:
        """Whether every row passes (proved or on samples): ``check`` exits 0 (without ``--require proved``)."""
        return self.kind != FAILS

    @property
    def proved(self) -> bool:
        return self.kind == PROVED

    @property
    def sampled_rows(self) -> list[str]:
        """The conditions that pass on samples only."""
        return [r.condition for r in self.rows if r.status == "pass" and r.evidence != PROVED]

    def counts(self) -> str:
        """The verdict with its counts, for ``ashc design``'s last line: 'proved (15/15 conditions of Problem 1)',
        'holds on samples only (12 of 15 conditions proved; sampled: a, b, c)' or 'no (13 of 15 conditions pass)'."""
        n, passed = len(self.rows), sum(r.status == "pass" for r in self.rows)
        proved = sum(r.status == "pass" and r.evidence == PROVED for r in self.rows)
        if self.kind == PROVED:
            return f"proved ({proved}/{n} conditions of Problem 1)"
        if self.kind == SAMPLED:
            return f"holds on samples only ({proved} of {n} conditions proved; sampled: {', '.join(self.sampled_rows)})"
        return f"no ({passed} of {n} conditions pass)"

    def text(self) -> str:
        """The verdict in words: 'proved', 'holds on samples only (sampled: a, b)' or 'no'."""
        if self.kind == PROVED:
            return "proved"
        if self.kind == SAMPLED:
            return "holds on samples only (sampled: " + ", ".join(self.sampled_rows) + ")"
        return "no"

    def line(self) -> str:
        """The last line of ``ashc check``."""
        return f"Problem 1 solved: {self.text()}"


def verdict(arts: dict[str, Artefact], stopped: tuple[str, AshcError] | None = None) -> Verdict:
    """Problem 1's verdict from the design artefacts.

    Parameters
    ----------
    arts : dict of str to Artefact
        The artefacts of the stages that completed.
    stopped : (stage, error), optional
        The stage whose design condition failed, and its error, if the design stopped early.

    Returns
    -------
    Verdict
        ``proved`` when every row passes with a proof, ``sampled`` when every row passes but some only on
        samples, ``fails`` otherwise; and the rows.
    """
    rows = []
    optional = tuple(r for r in OPTIONAL_ROWS if r[3] in arts and r[4] in arts[r[3]].checks)
    for condition, label, requirement, stage, check in ROWS + optional:
        reference = cite(label)   # as the published paper numbers it (the labels are in docs/theory.md)
        if stage in arts and check in arts[stage].checks:
            chk = arts[stage].checks[check]
            value = float(chk.value) if np.isfinite(chk.value) else None
            rows.append(Row(condition, reference, requirement, "pass" if chk.passed else "fail", value, cite(chk.description), chk.evidence))
        elif stopped is not None and (getattr(stopped[1], "check", None) == check
                                      or (stopped[0] == stage and getattr(stopped[1], "check", None) is None)):
            # The failure is about this row (or about the stage as a whole, e.g. an unsupported case).
            rows.append(Row(condition, reference, requirement, "fail", None, stopped[1].line(), getattr(stopped[1], "evidence", "sampled")))
        else:
            reason = f"stage {stage} did not complete" if stopped is not None else f"no {stage} artefact"
            rows.append(Row(condition, reference, requirement, "not reached", None, reason))
    if stopped is not None and not any(r.status == "fail" for r in rows):
        rows.append(Row("design stage " + stopped[0], "-", "-", "fail", None, stopped[1].line(), getattr(stopped[1], "evidence", "sampled")))
    if not all(r.status == "pass" for r in rows):
        kind = FAILS
    elif all(r.evidence == PROVED for r in rows):
        kind = PROVED
    else:
        kind = SAMPLED
    return Verdict(kind, tuple(rows))


#: The scenario checks that test a guarantee of the design (a bound, a tolerance, an invariant level, the m-relation's
#: outputs, the state box of a region resting on it): one that fails on a run inside the certified region contradicts
#: the design.  (``tracking_settled`` and the deadlines test the controller's choice, not a guarantee.)
GUARANTEE_CHECKS = ("tracking_error_within_bound", "tracking_error_within_posterior_bound", "tracking_error_within_tolerance",
                    "tracking_w_below_level", "tracking_x_in_state_box", "m_relation_outputs_match")


def contradictions(art: Artefact) -> list[str]:
    """The guarantee checks (:data:`GUARANTEE_CHECKS`) a simulate artefact fails where the design claims them: the
    tracking ones only when the run started inside the certified region.

    Parameters
    ----------
    art : Artefact
        The simulate stage's artefact.

    Returns
    -------
    list of str
        "name = value" for each; empty when the runs agree with the design.
    """
    inside = bool(art.values.get("tracking/inside_certified_region", True))
    out = []
    for name in GUARANTEE_CHECKS:
        chk = art.checks.get(name)
        if chk is None or chk.passed or (name.startswith("tracking_") and not inside):
            continue
        out.append(f"{name} = {chk.value:.4g}" if np.isfinite(chk.value) else name)
    return out
