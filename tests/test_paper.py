"""Tests of ashc_cli.paper: the paper's numbers for the LaTeX labels the code cites."""

import json
import re

import pytest

from ashc_cli.paper import LABELS, cite
from ashc_cli.design.verdict import ROWS

from .conftest import CUK, ROOT, ashc


def test_labels_are_docs_labels_json():
    assert LABELS == json.loads((ROOT / "docs" / "labels.json").read_text())


@pytest.mark.parametrize("text, expected", [
    ("eq. SimuFuncCondi1", "eq. (6)"),
    ("Thm. mCondi (ii), Cor. mRelateGeo", "Theorem 6 (ii), Corollary 1"),
    ("eqs. mRelatSuffiDiff, mRelatSuffiIn", "eqs. (21a), (21b)"),
    ("Thm. mCondi, step 1", "Theorem 6, step 1"),
    ("eq. egLMI, Thm. StabiliseLyap", "eq. (28), Theorem 1"),
    ("Figs. Example_BoundedIn/Out", "Figs. 7, 8"),
    ("Assumption outputLipstchiz", "Assumption 1"),
    ("eqs. iota, egqLS, egErrorBound; Prop. condB", "eqs. (37), (43), (38); Proposition 1"),
    ("eq. notALabel and Thm. ErrorBound", "eq. notALabel and Theorem 2"),
])
def test_cite(text, expected):
    assert cite(text) == expected


#: A citation by LaTeX label: a kind word followed by a camel-case or underscored name.
LATEX_CITATION = re.compile(r"\b(?:eqs?\.|Thm\.|Prop\.|Cor\.|Def\.|Assumption|Figs?\.)\s+[a-z]*[A-Z_][A-Za-z0-9_]*")


def test_every_verdict_reference_is_a_paper_number():
    for _, label, *_ in ROWS:
        assert not LATEX_CITATION.search(cite(label)), label


@pytest.mark.slow
def test_check_and_help_cite_the_paper_numbers(tmp_path):
    proc = ashc("check", str(CUK), "--out", str(tmp_path))
    assert proc.returncode == 0, proc.stderr
    assert "eq. (6)" in proc.stdout and "Theorem 6 (i)" in proc.stdout
    assert not LATEX_CITATION.search(proc.stdout), proc.stdout
    for command in ("stabilise", "manifold", "kappa", "inverse", "delta", "bound", "simulate"):
        text = ashc(command, "--help").stdout
        assert not LATEX_CITATION.search(text), (command, text)
