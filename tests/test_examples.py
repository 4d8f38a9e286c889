"""Tests of ashc example (the ladder family) and of the numeric fast paths against the symbolic ones."""

import functools

import numpy as np
import pytest
import sympy as sp

from ashc_cli.design.artefacts import read_artefact
from ashc_cli.problem.examples import TOTALS, ladder, parameters
from ashc_cli.problem.model import NUMERIC_THRESHOLD, build_model
from ashc_cli.problem.spec import parse_spec_text

from .conftest import ashc


@pytest.mark.parametrize("stages", [1, 3])
def test_ladder_spec_is_the_documented_model(stages):
    # f(x, u) = A(u) x + b with A(u) = H^-1 (J(u) - D), J skew: check the skew part and the damping, with the
    # per-cell values the line's totals / N.
    model = build_model(parse_spec_text(ladder(stages)))
    n = 4 * stages
    assert model.n == n and model.m == 1 and model.p == 1
    assert model.spec.parameters == {"E": 10.0, "L": 1e-2 / stages, "C": 1e-2 / stages, "r": 0.2 / stages, "G_c": 0.02 / stages}
    H = np.diag([1e-2 / stages] * n)                         # L = C = 1e-2 / N
    for u in (0.0, 0.37, 1.0):
        A = np.array(model.substitute(model.f.jacobian(model.x).xreplace({model.u[0]: u})), dtype=float)
        HA = H @ A
        assert np.allclose(HA + HA.T, -2 * np.diag([0.2 / stages if j % 2 == 0 else 0.02 / stages for j in range(n)]))
    assert str(model.h[0]) == f"v{n}"
    # The decay rate 2 min(r/L, G_c/C) = 4 does not depend on N; the spec asks for half of it.
    assert model.spec.stabilisability.decay_rate == 2.0


@functools.cache
def ladder_model(stages: int):
    return build_model(parse_spec_text(ladder(stages)))


def dc_output(stages: int, u: float) -> float:
    """The equilibrium output v_4N at duty cycle u, from the spec's own expressions (not from examples.py's helper):
    f(x, u) = A x + b read off row by row (each row couples at most three states)."""
    model = ladder_model(stages)
    f = model.valued["f_bar"] + model.valued["g"] * sp.Matrix([u])
    column = {s: j for j, s in enumerate(model.x)}
    A, b = np.zeros((model.n, model.n)), np.zeros(model.n)
    for i, e in enumerate(f):
        for sym in e.free_symbols:
            A[i, column[sym]] = float(e.diff(sym))
        b[i] = float(e.xreplace({sym: 0 for sym in e.free_symbols}))
    return float(np.linalg.solve(A, -b)[-1])


@pytest.mark.parametrize("stages", [1, 16, 128])
def test_ladder_output_range_is_of_the_order_of_the_source_at_any_size(stages):
    # The totals of the line are fixed, so the DC output at a duty cycle barely depends on N: about E / (1 - u)
    # less the line's loss.  With per-cell losses fixed it decayed like exp(-2 N sqrt(r G_c)) (0.006 V at N = 64).
    E = TOTALS["E"]
    (lo, hi), = ladder_model(stages).spec.concrete.output_set
    assert lo == pytest.approx(dc_output(stages, 0.05), abs=1e-6) and hi == pytest.approx(dc_output(stages, 0.55), abs=1e-6)
    assert E <= lo < hi <= E / (1 - 0.55)
    assert lo == pytest.approx(E / 0.95, rel=0.02) and hi == pytest.approx(E / 0.45, rel=0.05)
    # Refining the line changes the output by less than 4 % from N = 1 on.
    assert abs(dc_output(stages, 0.3) - dc_output(1, 0.3)) < 0.04 * dc_output(1, 0.3)


def test_ladder_per_cell_values_are_the_totals_over_N():
    for stages in (1, 2, 7, 128):
        p = parameters(stages)
        assert p["E"] == TOTALS["E"]
        assert all(p[k] * stages == pytest.approx(TOTALS[k], rel=1e-15) for k in ("L", "C", "r", "G_c"))


@pytest.mark.slow
def test_numeric_and_symbolic_paths_agree_on_a_mid_size_ladder(tmp_path):
    # n = 12 is the largest size still designed symbolically by default (NUMERIC_THRESHOLD); force both ways.
    assert NUMERIC_THRESHOLD == 12
    spec = tmp_path / "ladder_3.yaml"
    ashc("example", "ladder", "--stages", "3", "--output", str(spec), check=True)
    ashc("design", str(spec), "--out", str(tmp_path / "sym"), "--symbolic", check=True)
    ashc("design", str(spec), "--out", str(tmp_path / "num"), "--numeric", check=True)
    sym = {s: read_artefact(tmp_path / "sym" / f"{s}.h5") for s in ("manifold", "kappa", "inverse", "bound")}
    num = {s: read_artefact(tmp_path / "num" / f"{s}.h5") for s in ("manifold", "kappa", "inverse", "bound")}
    assert sym["manifold"].meta["method"].startswith("closed form")
    assert num["manifold"].meta["method"].startswith("Newton continuation")
    # The numeric path keeps p, dp/dxi, kappa and dp/dxi delta as Chebyshev series; the symbolic one as formulas.
    assert set(num["manifold"].series) == {"p", "dp_dxi"} and set(num["kappa"].series) == {"kappa", "dkappa_dxi"}
    assert set(num["bound"].series) == {"dp_delta"} and not sym["manifold"].series
    # Their formulas (what simulate and eval read) are the series up to round-off, and checked as such.
    assert num["manifold"].values["p_formula_deviation"] < 1e-12 and num["kappa"].values["kappa_formula_deviation"] < 1e-12
    assert "the Chebyshev series and its formula" in num["manifold"].checks["pde_residual"].description
    assert np.allclose(sym["manifold"].values["p_grid"], num["manifold"].values["p_grid"], rtol=1e-8, atol=1e-9)
    for key in ("alpha_h_sampled", "dbar_q0_sampled", "dbar_q0_identity"):
        assert num["bound"].values[key] == pytest.approx(sym["bound"].values[key], rel=1e-7), key
    # dbar_q0 and G use the proved upper bound of the branch and bound, which stops once its gap is below
    # 1e-6 relative, on each path's own formula for p: the two bounds agree to that gap, not to 1e-7.
    for key in ("dbar_q0", "gain"):
        assert num["bound"].values[key] == pytest.approx(sym["bound"].values[key], rel=3e-6), key
    assert num["inverse"].values["left_inverse_residual"] < 1e-9
    # A meaningful design at this size: kappa(V) of the order of E = 10 V, covering Y.
    (k_lo, k_hi), = num["kappa"].values["kappa_range"]
    (y_lo, y_hi), = num["inverse"].values["Y"]
    assert 5.0 < k_lo <= y_lo < y_hi <= k_hi < 30.0
    # The series' formulas are proved the way the closed forms are (the PDE residual is an identity for the
    # closed form only, and m is an interpolant on the numeric path, so conditions (i), (ii) stay sampled there).
    for stage in ("kappa", "bound"):
        for name, chk in sym[stage].checks.items():
            assert num[stage].checks[name].evidence == chk.evidence == "proved", (stage, name)
    assert num["manifold"].checks["l_in_U"].evidence == "proved"
    assert all(num["inverse"].checks[name].evidence == "proved" for name in ("kappa_monotone", "V_covers_Y", "m_real_on_Y"))


def test_scaled_reactances_leave_the_numeric_manifold_unchanged(tmp_path):
    # The equilibria do not depend on L and C, which only scale the terms of f (by 1/L, 1/C): the fit must reach
    # pde_tolerance at the same degree, its residual being judged against the size of those terms.  (Judged
    # against 1, the fit of the 512-state ladder, whose terms reach 1e5, never met the tolerance.)
    from ashc_cli.design.pipeline import run

    text = ladder(3)
    small = text.replace("L: 0.0033333333333333335", "L: 3.3333333333333335e-07").replace("C: 0.0033333333333333335", "C: 3.3333333333333335e-07")
    assert small != text
    arts = [run(parse_spec_text(t), tmp_path / name, ["manifold"], numeric=True)["manifold"] for t, name in ((text, "a"), (small, "b"))]
    assert arts[0].meta["method"].split(" (")[0] == arts[1].meta["method"].split(" (")[0]
    assert arts[1].values["residual_scale"] > 1e3 * arts[0].values["residual_scale"]
    assert np.allclose(arts[0].values["p_grid"], arts[1].values["p_grid"], rtol=1e-9, atol=1e-9)


# --- the shipped specs ------------------------------------------------------------------------------------------


def test_the_example_specs_ship_inside_the_package_and_are_the_repositorys():
    from ashc_cli.problem.examples import SHIPPED, shipped

    from .conftest import ROOT

    assert SHIPPED.parent.name == "ashc_cli" and SHIPPED.is_dir()                  # package data, not the repository
    assert (ROOT / "specs").resolve() == SHIPPED.resolve()                           # specs/ is the link to them
    assert '"specs/*.yaml"' in (ROOT / "pyproject.toml").read_text(encoding="utf-8")  # and the wheel takes them
    names = shipped()
    assert "cuk_converter" in names and len(names) == len(list(SHIPPED.glob("*.yaml"))) >= 10
    assert all(names.values()), [n for n, d in names.items() if not d]             # each says what it is


def test_ashc_example_lists_and_writes_a_shipped_spec(tmp_path):
    from ashc_cli.problem.examples import SHIPPED

    listing = ashc("example", "--list", check=True).stdout.splitlines()
    assert any(line.startswith("cuk_converter ") and "Cuk converter" in line for line in listing)
    assert any(line.startswith("ladder ") and "--stages N" in line for line in listing)
    assert ashc("example", "cuk", check=True).stdout == (SHIPPED / "cuk_converter.yaml").read_text(encoding="utf-8")
    out = tmp_path / "mine.yaml"
    assert ashc("example", "quarter", "--output", str(out), check=True).stdout.strip() == f"{out}: the shipped spec quarter_car"
    assert parse_spec_text(out.read_text(encoding="utf-8")).name == "quarter_car"
    # rc_ladder without --stages is the shipped 5-node spec; with it, the family
    assert "name: rc_ladder\n" in ashc("example", "rc_ladder", check=True).stdout
    assert "rc_ladder_3" in ashc("example", "rc_ladder", "--stages", "3", check=True).stdout
    for args, message in ((["cu"], "error: KIND: 'cu' names 4 shipped specs"), (["nothing"], "error: KIND: 'nothing' is no example"),
                          (["cuk", "--stages", "2"], "error: --stages: 2; expected no --stages for a shipped spec")):
        proc = ashc("example", *args)
        assert proc.returncode == 2 and proc.stderr.startswith(message), (args, proc.stderr)


def test_the_ladder_with_task_is_the_same_plant_with_the_task_and_other_families_refuse_it(tmp_path):
    # --task appends LADDER_TASK to the same spec (every other key unchanged); with another family or a shipped spec
    # it is refused, naming the option, before anything is written
    plain, tasked = parse_spec_text(ladder(3)), parse_spec_text(ladder(3, task=True))
    assert plain.task is None and tasked.task is not None
    assert tasked.task.avoid[0].set == [[23.5, 30.0]] and tasked.task.planner.kind == "grid"
    assert plain.concrete == tasked.concrete and plain.abstract == tasked.abstract
    for args in (["chain", "--stages", "2"], ["cuk"]):
        proc = ashc("example", *args, "--task", "--output", str(tmp_path / "x.yaml"))
        assert proc.returncode == 2 and proc.stderr.strip().splitlines()[-1].startswith("error: --task: with"), proc.stderr
        assert not (tmp_path / "x.yaml").exists()
