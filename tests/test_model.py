"""Tests of the symbolic and numeric systems (ashc_cli.problem.model)."""

import numpy as np
import pytest
import sympy as sp

from ashc_cli.errors import SpecError
from ashc_cli.problem.model import build_model, lambdify
from ashc_cli.problem.spec import load_spec, parse_spec_text

from .conftest import CUK


def test_cuk_model_shapes_and_C():
    model = build_model(load_spec(CUK))
    assert (model.n, model.m, model.p, model.n_hat, model.m_hat) == (4, 1, 1, 1, 1)
    assert np.array_equal(model.C, [[0, 0, 0, 1]])
    # Parameters stay symbols in formulas and carry their sign.
    E = model.params["E"]
    assert E.is_positive and E in model.f_bar[0].free_symbols
    # ERRATA item 1: row 3 of g is -x2/L_3.
    assert model.g[2] == -model.x[1] / model.params["L_3"]


def test_nonlinear_h_has_no_C():
    text = CUK.read_text().replace('h: ["x4"]', 'h: ["x4**2"]')
    assert build_model(parse_spec_text(text)).C is None


def test_expression_may_not_use_other_side_names():
    text = CUK.read_text().replace('"x1/C_2"', '"xi/C_2"')
    with pytest.raises(SpecError, match=r"concrete.f_bar\[1\]: uses xi"):
        build_model(parse_spec_text(text))


def test_lambdify_broadcasts_and_marks_non_real():
    a, b = sp.symbols("a b", real=True)
    f = lambdify(sp.Matrix([[a + b, 1], [sp.sqrt(a), b]]), [a, b])
    out = f(np.array([1.0, 4.0, -1.0]), 2.0)
    assert out.shape == (2, 2, 3)
    assert np.allclose(out[0, 1], 1.0)
    assert np.allclose(out[1, 0, :2], [1.0, 2.0]) and np.isnan(out[1, 0, 2])


def test_cse_skipped_only_for_long_lists_of_small_expressions():
    from ashc_cli.problem.model import _worth_cse, compile_flat

    x = sp.symbols("x0:100", real=True)
    small = [x[i] - 2 * x[i + 1] for i in range(99)]
    assert not _worth_cse(small) and _worth_cse(small[:10])
    assert _worth_cse(small + [sp.Add(*[sp.sin(s) ** 2 for s in x[:20]])])
    f = compile_flat(small, x)
    assert np.allclose(f(*np.arange(100.0)), [i - 2 * (i + 1) for i in range(99)])
