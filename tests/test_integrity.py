"""Artefact integrity under faults: a run killed mid-stage, stale and foreign upstream artefacts."""

import os
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from ashc_cli.design.artefacts import read_artefact
from ashc_cli.errors import ArtefactError
from ashc_cli.design.pipeline import DESIGN, check_upstream, run, staleness
from ashc_cli.problem.spec import load_spec, parse_spec_text

from .conftest import CUK_PAPER_M, ROOT


def test_kill_during_a_stage_leaves_artefacts_intact(paper_out, tmp_path):
    out = tmp_path / "out"
    shutil.copytree(paper_out, out)
    before = {p.name: p.read_bytes() for p in out.glob("*.h5")}
    exe = Path(sys.executable).with_name("ashc")
    proc = subprocess.Popen([str(exe), "design", str(CUK_PAPER_M), "--out", str(out), "--force"], cwd=ROOT,
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env={**os.environ, "PYTHONUNBUFFERED": "1"})
    # Wait for the second stage to finish, then kill while the later (slower) stages run.
    for line in proc.stderr:
        if line.startswith("kappa"):
            break
    time.sleep(0.3)
    proc.send_signal(signal.SIGKILL)
    proc.wait(timeout=60)
    assert proc.returncode == -signal.SIGKILL
    spec = load_spec(CUK_PAPER_M)
    for name, old in before.items():
        path = out / name
        art = read_artefact(path)  # every artefact is readable: old or new, never half-written
        assert art.provenance["spec_sha256"] == spec.sha256
        assert path.read_bytes() == old or art.stage in ("stabilise", "manifold", "kappa", "inverse", "delta")
    # The next run cleans up leftovers and reruns exactly the stale stages.
    stale = {s for s in DESIGN if staleness(spec, out, s) is not None}
    seen = []
    run(spec, out, DESIGN, on_stage=lambda r: seen.append((r.stage, r.status)))
    assert {s for s, status in seen if status == "ran"} == stale
    assert not list(out.glob(".*.tmp"))


def test_frozen_refuses_a_stale_upstream_and_names_it(paper_out, tmp_path):
    out = tmp_path / "out"
    shutil.copytree(paper_out, out)
    spec = load_spec(CUK_PAPER_M)
    run(spec, out, ["bound"], frozen=True)  # all up to date: fine
    (out / "manifold.h5").unlink()
    with pytest.raises(ArtefactError, match=r"manifold.h5: is not up to date \(no artefact yet\); expected run `ashc design SPEC` first"):
        run(spec, out, ["bound"], frozen=True)
    assert not (out / "manifold.h5").exists()


def test_foreign_upstream_is_refused(paper_design):
    other = parse_spec_text(CUK_PAPER_M.read_text().replace("E: 12.0", "E: 24.0"))
    with pytest.raises(ArtefactError, match=r"stabilise.h5: was made from another spec.*rerun `ashc stabilise SPEC`"):
        check_upstream(other, "bound", paper_design)
    check_upstream(load_spec(CUK_PAPER_M), "bound", paper_design)  # its own spec: accepted


def test_foreign_schema_is_stale(paper_out, tmp_path, monkeypatch):
    import ashc_cli.design.pipeline as pipeline

    out = tmp_path / "out"
    shutil.copytree(paper_out, out)
    monkeypatch.setattr(pipeline, "SCHEMA_VERSION", 999)
    assert "schema" in staleness(load_spec(CUK_PAPER_M), out, "stabilise")
