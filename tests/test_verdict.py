"""Tests of the Problem 1 verdict (ashc_cli.design.verdict) and `ashc check` through the real entry point."""

import dataclasses
import json
import re

import pytest

from ashc_cli.errors import DesignError
from ashc_cli.design.verdict import FAILS, PROVED, ROWS, SAMPLED, verdict

from .conftest import CUK_PAPER_M, SPECS, ashc


def test_all_rows_pass_for_the_paper_design(paper_design):
    result = verdict(paper_design)
    assert result.kind == PROVED and result.solved and result.proved
    assert len(result.rows) == len(ROWS)
    assert result.sampled_rows == []
    assert result.line() == "Problem 1 solved: proved"
    by_name = {r.condition: r for r in result.rows}
    assert by_name["stabilisability certificate (LMI margin)"].value < 0
    assert by_name["Assumption 1: h Lipschitz"].value == 1.0  # h = x4: ||C||_2 = 1


def _with_evidence(arts, stage, check, evidence):
    """A copy of the artefacts with one check's evidence changed (the value and pass/fail kept)."""
    art = arts[stage]
    checks = {**art.checks, check: dataclasses.replace(art.checks[check], evidence=evidence)}
    return {**arts, stage: dataclasses.replace(art, checks=checks)}


def test_one_sampled_row_makes_the_verdict_sampled_and_names_it(paper_design):
    # Every row passes, but one only on samples: never "proved", and the line names the row.
    arts = _with_evidence(paper_design, "inverse", "condition_ii", SAMPLED)
    result = verdict(arts)
    assert result.kind == SAMPLED and result.solved and not result.proved
    assert result.sampled_rows == ["condition (ii)"]
    assert result.line() == "Problem 1 solved: holds on samples only (sampled: condition (ii))"
    assert result.counts() == "holds on samples only (14 of 15 conditions proved; sampled: condition (ii))"
    # The same for a row that enters G (the LMI) and for the certified region.
    for stage, check in (("stabilise", "lmi_margin"), ("bound", "certified_region"), ("bound", "alpha_h")):
        assert verdict(_with_evidence(paper_design, stage, check, SAMPLED)).kind == SAMPLED


def test_a_failed_condition_is_attributed_to_its_row(paper_design):
    partial = {k: v for k, v in paper_design.items() if k in ("stabilise", "manifold", "kappa")}
    err = DesignError("abstract.domain", "kappa(V) does not cover Y", "a larger V", check="V_covers_Y")
    result = verdict(partial, ("inverse", err))
    assert result.kind == FAILS and not result.solved
    assert result.line() == "Problem 1 solved: no"
    status = {r.condition: r.status for r in result.rows}
    assert status["V covers Y"] == "fail"
    assert status["condition (i)"] == "not reached" and status["condition (B)"] == "not reached"
    assert status["invariance PDE residual"] == "pass"


def test_a_failure_without_a_row_is_still_a_failure(paper_design):
    partial = {k: paper_design[k] for k in ("stabilise",)}
    result = verdict(partial, ("manifold", DesignError("abstract.phi_bar", "unsupported")))
    assert result.kind == FAILS and any(r.status == "fail" for r in result.rows)


def test_check_cli_proved_and_no(tmp_path):
    proc = ashc("check", str(CUK_PAPER_M), "--out", str(tmp_path / "ok"), "--json", "--require", "proved")
    assert proc.returncode == 0, proc.stderr
    data = json.loads(proc.stdout)
    assert data["solved"] is True and data["verdict"] == "proved" and data["sampled"] == []
    assert all(r["status"] == "pass" and r["evidence"] == "proved" for r in data["rows"])

    spec = tmp_path / "short_V.yaml"
    spec.write_text(CUK_PAPER_M.read_text().replace("domain: [[0, 0.95]]", "domain: [[0, 0.9]]"))
    proc = ashc("check", str(spec), "--out", str(tmp_path / "no"))
    assert proc.returncode == 3
    assert "Problem 1 solved: no" in proc.stdout
    assert re.search(r"fail +(proved|sampled) +V covers Y", proc.stdout), proc.stdout
    data = json.loads(ashc("check", str(spec), "--out", str(tmp_path / "no"), "--json").stdout)
    assert data["verdict"] == "fails" and data["solved"] is False


@pytest.mark.slow
def test_check_cli_on_samples_only_exits_0_unless_proved_is_required(tmp_path):
    # valve_tanks: m has square roots of two tank levels, so eq. (10), the inverse rows and m real on Y are sampled.
    spec = SPECS / "valve_tanks.yaml"
    proc = ashc("check", str(spec), "--out", str(tmp_path / "d"), "--json")
    assert proc.returncode == 0, proc.stderr
    data = json.loads(proc.stdout)
    assert data["verdict"] == "sampled" and data["solved"] is True and data["sampled"]
    sampled = {r["condition"] for r in data["rows"] if r["evidence"] != "proved"}
    assert set(data["sampled"]) == sampled
    text = ashc("check", str(spec), "--out", str(tmp_path / "d"))
    last = text.stdout.strip().splitlines()[-1]
    assert last == "Problem 1 solved: holds on samples only (sampled: " + ", ".join(data["sampled"]) + ")"
    strict = ashc("check", str(spec), "--out", str(tmp_path / "d"), "--require", "proved")
    assert strict.returncode == 3
    assert "error: check: --require proved: the verdict holds on samples only" in strict.stderr
    # design's last line says the same; the published bound rests on proved rows only (none of the sampled rows
    # enters G), so G carries no "(sampled)"
    design = ashc("design", str(spec), "--out", str(tmp_path / "d"))
    assert design.returncode == 0
    assert ": holds on samples only (" in design.stdout and " (sampled) ||v||_inf" not in design.stdout
    assert "invariance PDE residual" not in data["sampled"]
