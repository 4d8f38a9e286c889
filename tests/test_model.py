"""Tests of the symbolic and numeric systems (ashc_cli.problem.model)."""

import numpy as np
import pytest
import sympy as sp

from ashc_cli.errors import SpecError
from ashc_cli.problem.model import build_model, lambdify
from ashc_cli.problem.spec import load_spec, parse_spec_text

from .conftest import CUK, TANH_INPUT


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


def test_a_plant_written_as_f_of_x_and_u_is_kept_whole_and_designed_with_q_zero():
    spec = parse_spec_text(TANH_INPUT)
    assert spec.interface.q == "zero"                      # the default for concrete.f: q = least_squares needs g
    model = build_model(spec)
    assert not model.affine and model.f_bar is None and model.g is None
    x1, x2, u = model.x[0], model.x[1], model.u[0]
    assert sp.simplify(model.f[1] - (-x2 - x2**3 / 3 + sp.tanh(u) + x1 / 5)) == 0
    # f(p(xi), l(xi)) of eq. (14a), Remark 4
    xi = model.xi[0]
    assert sp.simplify(model.f_on(sp.Matrix([xi, xi]), model.l)[1] - (-xi - xi**3 / 3 + sp.tanh(xi) + xi / 5)) == 0


def test_an_f_affine_in_u_is_split_into_f_bar_and_g():
    model = build_model(parse_spec_text(TANH_INPUT.replace("tanh(u)", "(1 + x1**2)*u")))
    x1, x2 = model.x
    assert model.affine
    assert sp.simplify(model.f_bar[1] - (-x2 - x2**3 / 3 + x1 / 5)) == 0 and model.f_bar[0] == -model.params["a"] * x1 + x2
    assert list(model.g) == [0, 1 + x1**2]


@pytest.mark.parametrize("edit, message", [
    (('  f: ["-a*x1 + x2", "-x2 - x2**3/3 + tanh(u) + 0.2*x1"]\n', '  f: ["-a*x1 + x2", "-x2 - x2**3/3 + tanh(u) + 0.2*x1"]\n  g: [["1"], ["0"]]\n'),
     r"concrete\.f: given with g; expected either f"),
    (('  f: ["-a*x1 + x2", "-x2 - x2**3/3 + tanh(u) + 0.2*x1"]\n', '  f_bar: ["-a*x1", "-x2"]\n'), r"concrete\.g: is missing; expected f_bar and g"),
    (('  f: ["-a*x1 + x2", "-x2 - x2**3/3 + tanh(u) + 0.2*x1"]\n', '  f: ["-a*x1 + x2"]\n'), r"concrete\.f: has 1 entries; expected 2"),
    (("tanh(u)", "tanh(xi)"), r"concrete\.f\[1\]: uses xi"),
    (("simulate:\n", "interface: {q: least_squares}\nsimulate:\n"), r"interface\.q: least_squares needs g\(x\)"),
])
def test_a_plant_written_as_f_is_refused_with_the_field_named(edit, message):
    with pytest.raises(SpecError, match=message):
        build_model(parse_spec_text(TANH_INPUT.replace(*edit)))
