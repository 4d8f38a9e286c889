"""Shared fixtures: the paper's Cuk converter designed once per test session.

``paper_design`` runs the design stages in-process on specs/cuk_converter_paper_M.yaml (the paper's M,
eq. egM, verified); ``cli_run`` runs the real ``ashc`` entry point (design + simulate) on
specs/cuk_converter.yaml (the tool's own LMI solution) into a temporary folder.
"""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest

from ashc_cli.problem.model import build_model
from ashc_cli.design.pipeline import DESIGN, run
from ashc_cli.problem.spec import load_spec

ROOT = Path(__file__).resolve().parents[1]
SPECS = ROOT / "specs"
CUK = SPECS / "cuk_converter.yaml"
CUK_PAPER_M = SPECS / "cuk_converter_paper_M.yaml"


def ashc(*args: str, check: bool = False, timeout: float = 600) -> subprocess.CompletedProcess:
    """Run the installed ``ashc`` console script (the real entry point)."""
    exe = Path(sys.executable).with_name("ashc")
    cmd = [str(exe)] if exe.exists() else [sys.executable, "-m", "ashc_cli"]
    proc = subprocess.run(cmd + list(args), capture_output=True, text=True, timeout=timeout, cwd=ROOT, env={**os.environ, "PYTHONWARNINGS": "ignore"})
    if check and proc.returncode != 0:
        raise AssertionError(f"ashc {' '.join(args)} exited {proc.returncode}:\n{proc.stdout}\n{proc.stderr}")
    return proc


def edited(path: Path, tmp_path: Path, *pairs: tuple[str, str], name: str = "edited.yaml") -> Path:
    """Write a copy of a spec with each (old, new) replacement applied (each must occur)."""
    text = path.read_text()
    for old, new in pairs:
        assert old in text, f"{old!r} not in {path.name}"
        text = text.replace(old, new)
    out = tmp_path / name
    out.write_text(text)
    return out


@pytest.fixture(scope="session")
def paper_spec():
    return load_spec(CUK_PAPER_M)


@pytest.fixture(scope="session")
def paper_model(paper_spec):
    return build_model(paper_spec)


@pytest.fixture(scope="session")
def paper_out(paper_spec, tmp_path_factory):
    """A session folder holding the artefacts of stabilise..bound for the paper's M."""
    out = tmp_path_factory.mktemp("paper_design")
    run(paper_spec, out, DESIGN)
    return out


@pytest.fixture(scope="session")
def paper_design(paper_spec, paper_out):
    """The artefacts of stabilise..bound for the paper's M, by stage (read back, all up to date)."""
    return run(paper_spec, paper_out, DESIGN)


@pytest.fixture(scope="session")
def cli_run(tmp_path_factory):
    """`ashc design` then `ashc simulate` on the Cuk spec through the real entry point."""
    out = tmp_path_factory.mktemp("cli_cuk")
    design = ashc("design", str(CUK), "--out", str(out), check=True)
    simulate = ashc("simulate", str(CUK), "--out", str(out), check=True)
    return {"out": out, "design": design, "simulate": simulate}


# A plant that is not input-affine (the paper's Remark 4), written fresh: the input enters through tanh.  On the manifold
# x1 = x2 = s with 0.8 s + s^3 / 3 = tanh(xi), so kappa(xi) = s and m(x) = atanh(0.8 x1 + x1^3 / 3) exactly.
TANH_INPUT = """
name: tanh_input
parameters: {a: 1.0}
concrete:
  states: [x1, x2]
  inputs: [u]
  f: ["-a*x1 + x2", "-x2 - x2**3/3 + tanh(u) + 0.2*x1"]
  h: [x1]
  input_bounds: [[-0.8, 0.8]]
  output_set: [[-0.4, 0.4]]
  state_box: [[-2, 2], [-2, 2]]
stabilisability: {method: polytopic_lmi, decay_rate: maximise}
abstract:
  states: [xi]
  inputs: [v]
  phi_bar: ["0"]
  l: ["xi"]
  domain: [[-0.7, 0.7]]
  pde_tolerance: 1.0e-10
simulate:
  tracking:
    t_final: 16.0
    xi0: [0.0]
    x0: on_manifold
    reference_levels: [0.2, -0.25]
    dwell: 8.0
    abstract_controller: {kind: setpoint, gain: 2.0, v_max: 0.15}
  m_relation:
    x0: [0.05, -0.1]
    u: ["0.5*sin(t)"]
    t_final: 8.0
"""
