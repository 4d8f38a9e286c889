"""Tests of the Problem 1 verdict (ashc_cli.verdict) and `ashc check` through the real entry point."""

import json
import re

from ashc_cli.errors import DesignError
from ashc_cli.verdict import ROWS, verdict

from .conftest import CUK_PAPER_M, ashc


def test_all_rows_pass_for_the_paper_design(paper_design):
    solved, rows = verdict(paper_design)
    assert solved
    assert len(rows) == len(ROWS)
    by_name = {r.condition: r for r in rows}
    assert by_name["stabilisability certificate (LMI margin)"].value < 0
    assert by_name["Assumption 1: h Lipschitz"].value == 1.0  # h = x4: ||C||_2 = 1


def test_a_failed_condition_is_attributed_to_its_row(paper_design):
    partial = {k: v for k, v in paper_design.items() if k in ("stabilise", "manifold", "kappa")}
    err = DesignError("abstract.domain", "kappa(V) does not cover Y", "a larger V", check="V_covers_Y")
    solved, rows = verdict(partial, ("inverse", err))
    assert not solved
    status = {r.condition: r.status for r in rows}
    assert status["V covers Y"] == "fail"
    assert status["condition (i)"] == "not reached" and status["condition (B)"] == "not reached"
    assert status["invariance PDE residual"] == "pass"


def test_a_failure_without_a_row_is_still_a_failure(paper_design):
    partial = {k: paper_design[k] for k in ("stabilise",)}
    solved, rows = verdict(partial, ("manifold", DesignError("abstract.phi_bar", "unsupported")))
    assert not solved and any(r.status == "fail" for r in rows)


def test_check_cli_yes_and_no(tmp_path):
    proc = ashc("check", str(CUK_PAPER_M), "--out", str(tmp_path / "ok"), "--json")
    assert proc.returncode == 0, proc.stderr
    data = json.loads(proc.stdout)
    assert data["solved"] is True and all(r["status"] == "pass" for r in data["rows"])

    spec = tmp_path / "short_V.yaml"
    spec.write_text(CUK_PAPER_M.read_text().replace("domain: [[0, 0.95]]", "domain: [[0, 0.9]]"))
    proc = ashc("check", str(spec), "--out", str(tmp_path / "no"))
    assert proc.returncode == 3
    assert "Problem 1 solved: no" in proc.stdout
    assert re.search(r"fail +(proved|sampled) +V covers Y", proc.stdout), proc.stdout
