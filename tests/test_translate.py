"""The interface's law printed from the compiled loops' own source (ashc_cli/outputs/translate.py): every law the
export prints translates, what lies outside the subset is refused by name and line, and the C it prints computes
what numba computes, bit for bit (the same operations in the same order, no pseudo-inverse involved)."""

from __future__ import annotations

import ctypes
import inspect
import subprocess

import numpy as np
import pytest

from ashc_cli.closedloop import interface
from ashc_cli.closedloop.laws import F1
from ashc_cli.errors import Untranslatable
from ashc_cli.outputs import printers, translate

from .test_export import CC, CFLAGS, needs_cc

_P = ctypes.POINTER(ctypes.c_double)


def test_every_printed_law_translates_and_declares_what_it_writes():
    known: dict = {}
    for fn in printers.LAWS:
        name = getattr(fn, "py_func", fn).__name__
        if name != "pinv_into":                          # C has its own (Jacobi SVD); numpy's pinv in Python
            text = "\n".join(translate.c_function(fn, known))
            assert f"void {name}(" in text
        known[name] = translate.header(fn, known)
    written = {name: [p for p, _, w in head if w] for name, head in known.items()}
    assert written["saturate"] == ["u"] and written["feedback_of"] == ["feedback"]
    assert written["q_of"] == ["q", "ltg", "ltd", "pg"] and written["apply"] == ["corr", "u"]
    # apply hands u to saturate, which writes it: so apply writes u, and l stays const
    assert "const double *l" in "\n".join(translate.c_function(interface.apply, known))


def _outside_the_subset(x: F1, out: F1):
    k = 0
    while k < x.size:
        out[k] = x[k]
        k += 1


def _not_annotated(x, out: F1):
    out[0] = x[0]


def _calls_numpy(x: F1, out: F1):
    out[0] = np.sum(x)


@pytest.mark.parametrize("fn, words", [(_outside_the_subset, ["_outside_the_subset", f"test_translate.py:{inspect.getsourcelines(_outside_the_subset)[1] + 2}", "While"]),
                                       (_not_annotated, ["_not_annotated", "'x'", "annotation"]),
                                       (_calls_numpy, ["_calls_numpy", "np.sum(x)"])])
def test_a_law_outside_the_subset_is_refused_by_name_and_line(fn, words):
    with pytest.raises(Untranslatable) as err:
        translate.c_function(fn, {})
    for word in words:
        assert word in str(err.value)


def test_python_form_is_the_source_without_decorator_and_with_a_short_docstring():
    text = translate.python_source(interface.feedback_of)
    assert text.startswith("def feedback_of(K, x, pm, feedback):")
    assert "@njit" not in text and "Parameters" not in text
    assert "s += K[j, i] * (x[i] - pm[i])" in text
    space: dict = {}
    exec(compile(text, "<printed>", "exec"), space)           # the printed text is runnable Python
    K, x, pm = np.array([[1.0, 2.0], [3.0, -1.0]]), np.array([0.5, 2.0]), np.array([0.25, -1.0])
    got, want = np.empty(2), np.empty(2)
    space["feedback_of"](K, x, pm, got)
    interface.feedback_of(K, x, pm, want)
    np.testing.assert_array_equal(got, want)


@pytest.fixture(scope="module")
def c_laws(tmp_path_factory):
    if CC is None:
        pytest.skip("no C compiler")
    known: dict = {}
    lines = ["#include <math.h>", *translate.C_MIN_MAX, ""]
    for fn in (interface.saturate, interface.feedback_of, interface.times, interface.apply):
        lines += translate.c_function(fn, known, static=False)
        known[fn.py_func.__name__] = translate.header(fn, known)
    folder = tmp_path_factory.mktemp("laws")
    (folder / "laws.c").write_text("\n".join(lines))
    lib = folder / "laws.so"
    proc = subprocess.run([CC, *CFLAGS, "-Wextra", "-pedantic", "-shared", "-fPIC", "-o", str(lib), str(folder / "laws.c"), "-lm"],
                          capture_output=True, text=True)
    assert proc.returncode == 0, proc.stderr
    return ctypes.CDLL(str(lib))


def _p(a: np.ndarray):
    return a.ctypes.data_as(_P)


@needs_cc
def test_the_printed_c_computes_what_numba_computes_bit_for_bit(c_laws):
    rng = np.random.default_rng(0)
    i = ctypes.c_int
    U = np.array([[-1.0, 1.0], [0.0, 2.0], [-3.0, -1.0]])
    for trial in range(300):
        m, n = 3, 4
        K = rng.normal(size=(m, n))
        x, pm = rng.normal(size=n), rng.normal(size=n)
        want, got = np.empty(m), np.empty(m)
        interface.feedback_of(K, x, pm, want)
        c_laws.feedback_of(_p(K), i(m), i(n), _p(x), i(n), _p(pm), i(n), _p(got), i(m))
        np.testing.assert_array_equal(got, want)
        q, v = rng.normal(size=(m, 2)), rng.normal(size=2)
        interface.times(q, v, want)
        c_laws.times(_p(q), i(m), i(2), _p(v), i(2), _p(got), i(m))
        np.testing.assert_array_equal(got, want)
        # saturation at its edges: a zero correction, l on U's boundary, a NaN, every mode
        l = rng.uniform(U[:, 0], U[:, 1])
        feedback, qv = rng.normal(scale=3.0, size=m), rng.normal(scale=3.0, size=m)
        if trial % 7 == 0:
            feedback[trial % m], qv[trial % m] = 0.0, 0.0
        if trial % 11 == 0:
            l[1] = U[1, 1]
        if trial % 13 == 0:
            qv[0] = np.nan
        s = float(rng.choice([1.0, 0.5, 0.0]))
        for sat in (0, 1, 2):
            cw, cg = np.empty(m), np.empty(m)
            interface.apply(l, feedback, qv, s, U, sat, cw, want)
            c_laws.apply(_p(l), i(m), _p(feedback), i(m), _p(qv), i(m), ctypes.c_double(s), _p(U), i(m), i(2), i(sat),
                         _p(cg), i(m), _p(got), i(m))
            np.testing.assert_array_equal(got, want)
            np.testing.assert_array_equal(cg, cw)
