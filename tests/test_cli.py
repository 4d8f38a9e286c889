"""Tests of the command line through the real `ashc` entry point (the contract of cli.md)."""

import json

import pytest

from .conftest import CUK, CUK_PAPER_M, ashc

SUMMARY_KEYS = {
    "stabilise": ["lambda", "M", "lmi_margin"],
    "manifold": ["p", "residual"],
    "kappa": ["kappa"],
    "inverse": ["V", "m", "left_inverse_residual", "condition_ii"],
    "delta": ["delta", "b", "c", "min_singular_value"],
    "bound": ["alpha_h", "epsilon", "dbar_q0", "dbar_ls", "gain"],
}


def test_design_progress_lines(cli_run):
    out = cli_run["design"].stdout.splitlines()
    stages = [line.split()[0] for line in out[:6]]
    assert stages == list(SUMMARY_KEYS)
    assert all(" s  " in line for line in out[:6])
    assert "checks passed" in out[-1]


def test_design_skips_up_to_date_stages(cli_run):
    again = ashc("design", str(CUK), "--out", str(cli_run["out"]), check=True)
    assert all("up to date" in line for line in again.stdout.splitlines()[:6])


def test_summary_json_keys(cli_run):
    data = json.loads(ashc("summary", str(cli_run["out"]), "--json", check=True).stdout)
    for stage, keys in SUMMARY_KEYS.items():
        for key in keys:
            assert key in data[stage], f"{stage}.{key}"
    assert data["stabilise"]["lmi_margin"] <= 0
    assert data["stabilise"]["lambda"] == 2.0
    tr = data["simulate"]["tracking"]
    for key in ("max_abs_error", "v_inf", "u_min", "u_max"):
        assert key in tr
    assert data["simulate"]["m_relation"]["max_abs_error"] < 1e-6


def test_eval_prints_the_contract_shape(cli_run):
    out = ashc("eval", str(cli_run["out"]), "p", "--at", "xi=0.6156", check=True).stdout.strip()
    assert out.startswith("p(xi=0.6156) = [1.3678")
    out = ashc("eval", str(cli_run["out"]), "m", "--at", "x1=10.3256,x2=2.0561,x3=-4.9785,x4=-6.9732", check=True).stdout.strip()
    assert out.startswith("m(") and out.endswith("]") and "0.3677" in out
    out = ashc("eval", str(cli_run["out"]), "kappa", "--at", "xi=0", check=True).stdout.strip()
    assert out == "kappa(xi=0) = [0]"
    data = json.loads(ashc("eval", str(cli_run["out"]), "c", "--at", "x1=1,x2=2,x3=3,x4=-4", "--json", check=True).stdout)
    assert data["value"] == [0.0]
    theta = ashc("eval", str(cli_run["out"]), "theta", "--at", "xi=0.5,x1=1,x2=2,x3=3,x4=-4", check=True).stdout
    assert theta.startswith("theta(") and theta.count(",") >= 3


@pytest.mark.parametrize(
    "args, code, fragment",
    [
        (["design", "no/such.yaml"], 2, "error: no/such.yaml: no such file"),
        (["eval", "/nonexistent", "p", "--at", "xi=1"], 5, "holds no ashc artefact"),
    ],
)
def test_errors_are_one_line_with_code(args, code, fragment):
    proc = ashc(*args)
    assert proc.returncode == code
    assert proc.stderr.count("\n") == 1 and fragment in proc.stderr
    assert "Traceback" not in proc.stderr


def test_bad_spec_one_line_and_debug_traceback(tmp_path):
    spec = tmp_path / "bad.yaml"
    spec.write_text(CUK.read_text().replace('"x1/C_2"', "\"__import__('os').system('touch pwned')\""))
    proc = ashc("design", str(spec), "--out", str(tmp_path / "o"))
    assert proc.returncode == 2
    assert proc.stderr.startswith("error: concrete.f_bar[1]: call of '__import__") and "is not allowed" in proc.stderr
    assert "Traceback" not in proc.stderr and not (tmp_path / "o").exists()
    debug = ashc("--debug", "design", str(spec), "--out", str(tmp_path / "o"))
    assert debug.returncode == 2 and "Traceback" in debug.stderr


def test_design_condition_exit_3(tmp_path):
    spec = tmp_path / "short_V.yaml"
    spec.write_text(CUK_PAPER_M.read_text().replace("domain: [[0, 0.95]]", "domain: [[0, 0.9]]"))
    proc = ashc("design", str(spec), "--out", str(tmp_path / "o"))
    assert proc.returncode == 3 and "SimuLocalRequire" in proc.stderr
    # The stages before the failing one were written and stay valid.
    assert (tmp_path / "o" / "kappa.h5").exists() and not (tmp_path / "o" / "inverse.h5").exists()


def test_help_explains():
    proc = ashc("--help", check=True)
    for word in ("design", "simulate", "summary", "eval", "Exit codes"):
        assert word in proc.stdout
    assert "eq. egLMI" in ashc("stabilise", "--help", check=True).stdout
