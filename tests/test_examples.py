"""Tests of ashc example (the ladder family) and of the numeric fast paths against the symbolic ones."""

import numpy as np
import pytest

from ashc_cli.artefacts import read_artefact
from ashc_cli.examples import ladder
from ashc_cli.model import NUMERIC_THRESHOLD, build_model
from ashc_cli.spec import parse_spec_text

from .conftest import ashc


@pytest.mark.parametrize("stages", [1, 3])
def test_ladder_spec_is_the_documented_model(stages):
    # f(x, u) = A(u) x + b with A(u) = H^-1 (J(u) - D), J skew: check the skew part and the damping.
    model = build_model(parse_spec_text(ladder(stages)))
    n = 4 * stages
    assert model.n == n and model.m == 1 and model.p == 1
    H = np.diag([1e-2] * n)                                  # L = C = 1e-2
    for u in (0.0, 0.37, 1.0):
        A = np.array(model.substitute(model.f.jacobian(model.x).xreplace({model.u[0]: u})), dtype=float)
        HA = H @ A
        assert np.allclose(HA + HA.T, -2 * np.diag([0.2 if j % 2 == 0 else 0.02 for j in range(n)]))
    assert str(model.h[0]) == f"v{n}"


def test_numeric_and_symbolic_paths_agree_on_a_mid_size_ladder(tmp_path):
    # n = 12 is the largest size still designed symbolically by default (NUMERIC_THRESHOLD); force both ways.
    assert NUMERIC_THRESHOLD == 12
    spec = tmp_path / "ladder_3.yaml"
    ashc("example", "ladder", "--stages", "3", "--output", str(spec), check=True)
    ashc("design", str(spec), "--out", str(tmp_path / "sym"), "--symbolic", check=True)
    ashc("design", str(spec), "--out", str(tmp_path / "num"), "--numeric", check=True)
    sym = {s: read_artefact(tmp_path / "sym" / f"{s}.h5") for s in ("manifold", "inverse", "bound")}
    num = {s: read_artefact(tmp_path / "num" / f"{s}.h5") for s in ("manifold", "inverse", "bound")}
    assert sym["manifold"].meta["method"].startswith("closed form")
    assert num["manifold"].meta["method"].startswith("Newton continuation")
    assert np.allclose(sym["manifold"].values["p_grid"], num["manifold"].values["p_grid"], rtol=1e-8, atol=1e-9)
    for key in ("alpha_h_sampled", "dbar_q0_sampled", "dbar_q0_identity"):
        assert num["bound"].values[key] == pytest.approx(sym["bound"].values[key], rel=1e-7), key
    # dbar_q0 and G use the proved upper bound of the branch and bound, which stops once its gap is below
    # 1e-6 relative, on each path's own formula for p: the two bounds agree to that gap, not to 1e-7.
    for key in ("dbar_q0", "gain"):
        assert num["bound"].values[key] == pytest.approx(sym["bound"].values[key], rel=3e-6), key
    assert num["inverse"].values["left_inverse_residual"] < 1e-9
