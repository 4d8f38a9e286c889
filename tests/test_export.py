"""Tests of ``ashc export`` (issue 15, the design as code): the C99 file and the numpy module against the tool.

Each exported function is compared with the tool's own evaluation at random points: p and kappa with the
stored formulas lambdified, m with the formula and the certified set (``inverse.m_domain``), the interface and
the abstract controller with the oracle's ``tracking_law`` (tests/oracle.py).  The C file is compiled with the
system compiler (``cc -std=c99 -Wall -Werror -O2``, as a shared library called through ctypes); the tests that
need it are skipped, saying so, when there is none.  The tracking scenario of each spec is integrated again
with the exported Python functions (scipy's DOP853 at simulate's tolerances) and must give simulate's
tracking error.
"""

from __future__ import annotations

import ctypes
import json
import importlib.util
import os
import re
import shutil
import subprocess
from pathlib import Path

import numpy as np
import pytest
import scipy.integrate as sint

from ashc_cli.errors import ArtefactError, SpecError
from ashc_cli.outputs.export import export_sources, interface_value, write_export
from ashc_cli.outputs.export_design import gather, require_current
from ashc_cli.outputs.printers import c_sources, python_source
from ashc_cli.problem.model import compile_terms
from ashc_cli.design.pipeline import design_model, load_all, run
from ashc_cli.problem.spec import Interface, load_spec
from ashc_cli.design.upstream import certified_set, outside_certified_set
from .oracle import tracking_law
from ashc_cli.design.stages.simulate import SAMPLE_DT, TRACKING_TOL, DesignTerms, sample_times
from ashc_cli.design.upstream import reference_state

from .conftest import CUK, SPECS, edited

#: tracking_law evaluates the plant's m, b and c at every x (DesignTerms.at_x), also off the set where m is real.
pytestmark = pytest.mark.filterwarnings("ignore:invalid value encountered in sqrt:RuntimeWarning")

#: The specs exported: one input and a least-squares q (Cuk, boost), two inputs with saturate: scale and a
#: 3 x 2 pseudo-inverse (bilinear), a synthesised feedback gain K (unstable linear).
NAMES = ("cuk_converter", "bilinear_two_input", "unstable_linear", "boost_converter")
#: Exported code against the tool, relative to the size of the quantity over the sample.
RTOL = 1e-12
POINTS = 200

CFLAGS = ["-std=c99", "-Wall", "-Werror", "-O2"]
_P = ctypes.POINTER(ctypes.c_double)


def _compiler() -> str | None:
    for name in (os.environ.get("CC"), "cc", "gcc", "clang"):
        if name and shutil.which(name):
            return shutil.which(name)
    return None


CC = _compiler()
needs_cc = pytest.mark.skipif(CC is None, reason="no C compiler found (CC, cc, gcc or clang): the exported C file is not compiled or tested")


def _ptr(a: np.ndarray):
    return a.ctypes.data_as(_P)


class CDesign:
    """The exported C file compiled as a shared library, with numpy wrappers of its functions."""

    def __init__(self, source: Path, dims: tuple[int, int, int, int, int], extra_args: bool = False):
        self.n, self.n_inputs, self.nh, self.mh, self.p = dims
        lib = source.with_suffix(".so")
        proc = subprocess.run([CC, *CFLAGS, "-shared", "-fPIC", "-o", str(lib), str(source), "-lm"], capture_output=True, text=True)
        assert proc.returncode == 0, proc.stderr
        self.lib = ctypes.CDLL(str(lib))
        self.lib.ashc_m.restype = ctypes.c_int
        for name in ("ashc_p", "ashc_kappa", "ashc_interface", "ashc_controller", "ashc_abstract_rhs"):
            getattr(self.lib, name).restype = None
        if extra_args:
            self.lib.ashc_controller.argtypes = [_P, _P, ctypes.c_double, ctypes.c_double, _P]

    @staticmethod
    def _in(a) -> np.ndarray:
        return np.ascontiguousarray(a, dtype=float)

    def p_map(self, xi):
        out = np.empty(self.n)
        self.lib.ashc_p(_ptr(self._in(xi)), _ptr(out))
        return out

    def kappa(self, xi):
        out = np.empty(self.p)
        self.lib.ashc_kappa(_ptr(self._in(xi)), _ptr(out))
        return out

    def m(self, x):
        out = np.empty(self.nh)
        status = self.lib.ashc_m(_ptr(self._in(x)), _ptr(out))
        return status, out

    def interface(self, xi, x, v):
        out = np.empty(self.n_inputs)
        self.lib.ashc_interface(_ptr(self._in(xi)), _ptr(self._in(x)), _ptr(self._in(v)), _ptr(out))
        return out

    def controller(self, xi, xi_ref, *gains):
        out = np.empty(self.mh)
        self.lib.ashc_controller(_ptr(self._in(xi)), _ptr(self._in(xi_ref)), *gains, _ptr(out))
        return out


class PyDesign:
    """The exported Python module, with the same wrappers as :class:`CDesign`."""

    def __init__(self, path: Path):
        spec = importlib.util.spec_from_file_location(f"exported_{path.stem}", path)
        self.mod = importlib.util.module_from_spec(spec)
        spec.loader.exec_module(self.mod)

    def p_map(self, xi):
        return self.mod.ashc_p(xi)

    def kappa(self, xi):
        return self.mod.ashc_kappa(xi)

    def m(self, x):
        return self.mod.ashc_m(x)

    def interface(self, xi, x, v):
        return self.mod.ashc_interface(xi, x, v)

    def controller(self, xi, xi_ref, *gains):
        return self.mod.ashc_controller(xi, xi_ref, *gains)


@pytest.fixture(scope="module")
def designs(cli_run, tmp_path_factory):
    """Each spec of NAMES designed and simulated (the Cuk converter: the session's `ashc design` + `simulate`)."""
    out = {}
    for name in NAMES:
        spec = load_spec(SPECS / f"{name}.yaml")
        if name == "cuk_converter":
            folder = cli_run["out"]
        else:
            folder = tmp_path_factory.mktemp(name)
            run(spec, folder, ["simulate"])
        arts = load_all(folder)
        model = design_model(spec, arts)
        out[name] = {"spec": spec, "arts": arts, "model": model, "plant": DesignTerms(model, arts), "folder": folder}
    return out


@pytest.fixture(scope="module")
def exported(designs, tmp_path_factory):
    """Each design written by write_export: {name: {"c": [paths], "python": [paths]}}."""
    root = tmp_path_factory.mktemp("exported")
    return {name: {lang: write_export(d["spec"], d["arts"], lang, root / name / f"{name}_design.{'c' if lang == 'c' else 'py'}")
                   for lang in ("c", "python")} for name, d in designs.items()}


def _dims(model):
    return model.n, model.m, model.n_hat, model.m_hat, model.p


def _implementations(which, name, designs, exported):
    model = designs[name]["model"]
    if which == "c":
        if CC is None:
            pytest.skip("no C compiler found (CC, cc, gcc or clang): the exported C file is not compiled or tested")
        return CDesign(exported[name]["c"][0], _dims(model))
    return PyDesign(exported[name]["python"][0])


def _uniform(rng, box, size=None):
    box = np.asarray(box, dtype=float)
    return box[:, 0] + rng.random((size, len(box)) if size else len(box)) * (box[:, 1] - box[:, 0])


def _normwise(got: np.ndarray, want: np.ndarray) -> float:
    """max |got - want| over the sample, relative to max |want| (per component)."""
    got, want = np.asarray(got, dtype=float), np.asarray(want, dtype=float)
    scale = np.maximum(np.abs(want).max(axis=0), 1e-300)
    return float((np.abs(got - want).max(axis=0) / scale).max())


def _interface_samples(d, rng, points=POINTS, q_kind=None, saturate=None):
    """Random (xi, x, xi_ref) with the tool's (v, u) from tracking_law.

    For the interface, v is tracking_law's own v for a random gain (1e-2 to 1e4 times the spec's) and bound
    (up to 1e3 v_max), so that u is saturated at some points and not at others; for the controller, the spec's
    gain and bound, with xi_ref in V near xi (v not clipped) or in V widened three times (v clipped).
    """
    spec, model, plant = d["spec"], d["model"], d["plant"]
    ctl = spec.simulate.tracking.abstract_controller
    q_kind = spec.interface.q if q_kind is None else q_kind
    saturate = spec.interface.saturate if saturate is None else saturate
    wide = model.V.mean(axis=1)[:, None] + 3 * (model.V - model.V.mean(axis=1)[:, None])
    rows = []
    for k in range(points):
        xi = _uniform(rng, model.V)
        p = plant.p_map(*xi)[:, 0]
        x = p + (k % 4) * rng.normal(size=model.n) * (0.02 + 0.2 * np.abs(p))   # on the manifold, then further off it
        v, u, *_ = tracking_law(plant, xi, x, _uniform(rng, model.V), ctl.gain * 10 ** rng.uniform(-2, 4), ctl.v_max * 10 ** rng.uniform(-2, 3),
                                q_kind, saturate)
        xi_ref = xi + (_uniform(rng, model.V) - xi) * 10 ** rng.uniform(-6, 0) if k % 2 else _uniform(rng, wide)
        v_ctl, *_ = tracking_law(plant, xi, x, xi_ref, ctl.gain, ctl.v_max, q_kind, saturate)
        rows.append((xi, x, v, u, xi_ref, v_ctl))
    return rows


# --- the generated text -------------------------------------------------------------------------------------


def test_export_is_deterministic_and_names_its_sources(designs):
    d = designs["cuk_converter"]
    first = export_sources(d["spec"], d["arts"], "c", "cuk")
    assert first == export_sources(d["spec"], d["arts"], "c", "cuk")
    assert set(first) == {"cuk.c", "cuk.h"}
    source, header = first["cuk.c"], first["cuk.h"]
    assert '#include "cuk.h"' in source and "#include <math.h>" in source
    assert d["spec"].sha256 in source and d["spec"].sha256 in header
    # No allocation, no library beyond math.h; parameters as named constants.
    assert not re.search(r"\b(malloc|calloc|realloc|alloca|free)\s*\(", source)
    assert [line for line in source.splitlines() if line.startswith("#include")] == ["#include <math.h>", '#include "cuk.h"']
    assert "#define PRM_E 12.0" in source and "#define PRM_G_L 0.0447" in source
    for proto in ("void ashc_p(const double *xi, double *p);", "void ashc_kappa(const double *xi, double *psi);",
                  "int ashc_m(const double *x, double *xi);",
                  "void ashc_interface(const double *xi, const double *x, const double *v, double *u);",
                  "void ashc_controller(const double *xi, const double *xi_ref, double *v);"):
        assert proto in header
    assert "#define ASHC_GAIN 80.0" in header and "#define ASHC_V_MAX 60.0" in header
    # m's certified set is exported as constants.
    box, _, _ = certified_set(d["arts"]["inverse"])
    assert f"ashc_m_domain[ASHC_N_OUTPUTS][2] = {{{{({float(box[0, 0])!r}), {float(box[0, 1])!r}}}}}" in source
    py = export_sources(d["spec"], d["arts"], "python", "cuk")["cuk.py"]
    assert "import numpy" in py and "scipy" not in py and "sympy" not in py and "ashc_cli" not in py


@needs_cc
@pytest.mark.parametrize("name", NAMES)
def test_c_compiles_without_warnings(name, designs, exported, tmp_path):
    # The C file alone (the header beside it), with every warning an error, -Wextra and -pedantic included.
    source = exported[name]["c"][0]
    proc = subprocess.run([CC, *CFLAGS, "-Wextra", "-pedantic", "-c", str(source), "-o", str(tmp_path / "design.o")], capture_output=True, text=True)
    assert proc.returncode == 0, proc.stderr
    # The header is usable on its own by a driver.
    driver = tmp_path / "driver.c"
    driver.write_text(f'#include "{exported[name]["c"][1].name}"\n#include <stdio.h>\nint main(void)\n{{\n'
                      "    double xi[ASHC_N_ABSTRACT_STATES], psi[ASHC_N_OUTPUTS];\n    int i;\n"
                      "    for (i = 0; i < ASHC_N_ABSTRACT_STATES; i++) xi[i] = 0.5 * (ashc_abstract_domain[i][0] + ashc_abstract_domain[i][1]);\n"
                      '    ashc_kappa(xi, psi);\n    printf("%.17g\\n", psi[0]);\n    return 0;\n}\n')
    exe = tmp_path / "driver"
    proc = subprocess.run([CC, *CFLAGS, "-I", str(source.parent), "-o", str(exe), str(driver), str(source), "-lm"], capture_output=True, text=True)
    assert proc.returncode == 0, proc.stderr
    model = designs[name]["model"]
    want = designs[name]["plant"].kappa(*model.V.mean(axis=1))[0, 0]
    assert float(subprocess.run([str(exe)], capture_output=True, text=True, check=True).stdout) == pytest.approx(want, rel=RTOL)


# --- exported functions against the tool --------------------------------------------------------------------


@pytest.mark.parametrize("which", ["c", "python"])
@pytest.mark.parametrize("name", NAMES)
def test_p_and_kappa_match_the_stored_formulas(which, name, designs, exported):
    impl = _implementations(which, name, designs, exported)
    d = designs[name]
    model, plant = d["model"], d["plant"]
    xi = _uniform(np.random.default_rng(0), model.V, POINTS)
    p_tool = plant.p_map(*xi.T)[:, 0, :].T
    kappa_tool = plant.kappa(*xi.T)[:, 0, :].T
    assert _normwise([impl.p_map(z) for z in xi], p_tool) <= RTOL
    assert _normwise([impl.kappa(z) for z in xi], kappa_tool) <= RTOL


@pytest.mark.parametrize("which", ["c", "python"])
@pytest.mark.parametrize("name", NAMES)
def test_m_only_where_certified(which, name, designs, exported):
    impl = _implementations(which, name, designs, exported)
    d = designs[name]
    model, arts = d["model"], d["arts"]
    box, _, _ = certified_set(arts["inverse"])
    m_tool = model.numeric(arts["inverse"].expr("m"), list(model.x))
    h_tool = model.numeric(arts["inverse"].expr("h"), list(model.x))
    rng = np.random.default_rng(1)
    inside, outside = [], 0
    for k in range(POINTS):
        # States near the manifold, some far off it: their outputs fall inside and outside m_domain.
        p = d["plant"].p_map(*_uniform(rng, model.V))[:, 0]
        x = p + rng.normal(size=model.n) * (0.05 + 0.5 * np.abs(p)) * (k % 3)
        status, xi = impl.m(x)
        y = h_tool(*x)[:, 0]
        if outside_certified_set(box, y):
            assert status == 1 and np.all(np.isnan(xi)), (x, y, status)
            outside += 1
        else:
            want = m_tool(*x)[:, 0]
            assert status == (0 if np.all(np.isfinite(want)) else 2)
            inside.append((xi, want))
    assert outside >= 10 and len(inside) >= 50
    got, want = (np.array(a) for a in zip(*inside))
    assert _normwise(got, want) <= RTOL
    # The ends of the certified set are inside (to DOMAIN_RTOL), a little beyond them outside (one output: move x
    # along a state h is linear in, from a point of the manifold, until h(x) is at the end, then beyond it).
    if model.p == 1:
        x_mid = d["plant"].p_map(*model.V.mean(axis=1))[:, 0]
        y_mid = h_tool(*x_mid)[0, 0]
        j = next(j for j, e in enumerate(np.eye(model.n)) if h_tool(*(x_mid + e))[0, 0] != y_mid)
        slope = h_tool(*(x_mid + np.eye(model.n)[j]))[0, 0] - y_mid
        lo, hi = box[0]
        width = max(1.0, hi - lo)
        for target, status in ((lo, 0), (hi, 0), (lo - 1e-6 * width, 1), (hi + 1e-6 * width, 1)):
            assert impl.m(x_mid + np.eye(model.n)[j] * (target - y_mid) / slope)[0] == status, (target, status)


@pytest.mark.parametrize("which", ["c", "python"])
@pytest.mark.parametrize("name", NAMES)
def test_interface_and_controller_match_tracking_law(which, name, designs, exported):
    impl = _implementations(which, name, designs, exported)
    d = designs[name]
    model = d["model"]
    rows = _interface_samples(d, np.random.default_rng(2))
    u_got = [impl.interface(xi, x, v) for xi, x, v, *_ in rows]
    u_want = [u for _, _, _, u, _, _ in rows]
    assert _normwise(u_got, u_want) <= RTOL
    v_got = [impl.controller(xi, near) for xi, _, _, _, near, _ in rows]
    v_want = [v for *_, v in rows]
    assert _normwise(v_got, v_want) <= RTOL
    # The sample covers saturated and unsaturated inputs, clipped and unclipped abstract inputs.
    U = model.U
    at_bound = np.array([np.any((u <= U[:, 0]) | (u >= U[:, 1])) for u in u_want])
    v_max = d["spec"].simulate.tracking.abstract_controller.v_max
    v_clipped = np.array([np.any(np.abs(v) >= v_max) for v in v_want])
    assert at_bound.sum() >= 10 and (~at_bound).sum() >= 10
    assert v_clipped.sum() >= 10 and (~v_clipped).sum() >= 10


@pytest.mark.parametrize("which", ["c", "python"])
@pytest.mark.parametrize("q_kind, saturate", [("zero", False), ("zero", True), ("least_squares", False), ("least_squares", "scale")])
def test_interface_variants_on_the_cuk_design(which, q_kind, saturate, designs, tmp_path):
    # The same design with the other interfaces (q = 0, no saturation, scale): the exported law follows the spec.
    d = designs["cuk_converter"]
    spec = d["spec"].model_copy(update={"interface": Interface(q=q_kind, saturate=saturate)})
    texts = export_sources(spec, d["arts"], which, "variant")
    for file_name, text in texts.items():
        (tmp_path / file_name).write_text(text)
    if which == "c":
        if CC is None:
            pytest.skip("no C compiler found (CC, cc, gcc or clang): the exported C file is not compiled or tested")
        impl = CDesign(tmp_path / "variant.c", _dims(d["model"]))
    else:
        impl = PyDesign(tmp_path / "variant.py")
    rows = _interface_samples(d, np.random.default_rng(3), points=80, q_kind=q_kind, saturate=saturate)
    assert _normwise([impl.interface(xi, x, v) for xi, x, v, *_ in rows], [u for _, _, _, u, _, _ in rows]) <= RTOL
    if which == "c" and q_kind == "zero":
        assert "(void)v;" in texts["variant.c"]   # q = 0: the interface does not read v


@pytest.mark.parametrize("which", ["c", "python"])
def test_controller_takes_gain_and_bound_when_the_spec_gives_none(which, designs, tmp_path):
    # Without simulate.tracking the controller's gain and v_max are arguments (bilinear: delta = I, two inputs).
    d = designs["bilinear_two_input"]
    spec = d["spec"].model_copy(update={"simulate": d["spec"].simulate.model_copy(update={"tracking": None})})
    texts = export_sources(spec, d["arts"], which, "free")
    for file_name, text in texts.items():
        (tmp_path / file_name).write_text(text)
    if which == "c":
        if CC is None:
            pytest.skip("no C compiler found (CC, cc, gcc or clang): the exported C file is not compiled or tested")
        assert "void ashc_controller(const double *xi, const double *xi_ref, double gain, double v_max, double *v);" in texts["free.h"]
        assert "ASHC_GAIN" not in texts["free.h"]
        impl = CDesign(tmp_path / "free.c", _dims(d["model"]), extra_args=True)
    else:
        impl = PyDesign(tmp_path / "free.py")
        assert not hasattr(impl.mod, "GAIN")
    rng = np.random.default_rng(4)
    got, want = [], []
    for _ in range(100):
        xi, xi_ref = _uniform(rng, d["model"].V), _uniform(rng, d["model"].V)
        gain, v_max = 10 ** rng.uniform(-1, 1), 10 ** rng.uniform(-1, 0.5)
        x = d["plant"].p_map(*xi)[:, 0]
        v, *_ = tracking_law(d["plant"], xi, x, xi_ref, gain, v_max, spec.interface.q, spec.interface.saturate)
        got.append(impl.controller(xi, xi_ref, gain, v_max))
        want.append(v)
    assert _normwise(got, want) <= RTOL


# --- ashc eval DIR u_w --------------------------------------------------------------------------------------


@pytest.mark.parametrize("name", NAMES)
def test_interface_value_for_eval(name, designs):
    d = designs[name]
    spec, _model = d["spec"], d["model"]
    names = [*spec.abstract.states, *spec.concrete.states, *spec.abstract.inputs]
    for xi, x, v, u, *_ in _interface_samples(d, np.random.default_rng(5), points=20):
        point = dict(zip(names, [*xi, *x, *v]))
        assert _normwise([interface_value(spec, d["arts"], point)], [u]) <= RTOL
    point = dict(zip(names, [*xi, *x, *v]))
    with pytest.raises(SpecError, match="needs a value for"):
        interface_value(spec, d["arts"], {k: w for k, w in point.items() if k != names[-1]})
    with pytest.raises(SpecError, match="unknown variable"):
        interface_value(spec, d["arts"], {**point, "nonsense": 1.0})


# --- the tracking scenario through the exported module --------------------------------------------------------


@pytest.mark.parametrize("name", NAMES)
def test_tracking_scenario_through_the_exported_module(name, designs, exported):
    # The closed loop of simulate's tracking run with the exported controller, abstract system and interface and
    # the plant's f_bar, g from the model (DOP853, simulate's tolerances, the same dwells and sample times): the
    # largest |psi - y| must be simulate's, to the integration tolerance.
    d = designs[name]
    spec, model, plant, arts = d["spec"], d["model"], d["plant"], d["arts"]
    mod = PyDesign(exported[name]["python"][0]).mod
    tr = spec.simulate.tracking
    plant_terms = compile_terms([model.f_bar, model.g, model.h], list(model.x), model.values)
    levels = [np.atleast_1d(np.asarray(level, dtype=float)) for level in tr.reference_levels]
    refs = [reference_state(model, plant, level, i, arts["kappa"].expr("kappa")) for i, level in enumerate(levels)]
    nh = model.n_hat
    xi0 = np.array(tr.xi0, dtype=float)
    z = np.r_[xi0, mod.ashc_p(xi0) if tr.x0 == "on_manifold" else np.array(tr.x0, dtype=float)]
    ts, zs, t0, k = [], [], 0.0, 0
    while t0 < tr.t_final - 1e-12:
        xi_ref = refs[min(k, len(levels) - 1)]
        t1 = tr.t_final if k >= len(levels) - 1 else min(tr.t_final, (k + 1) * tr.dwell)

        def rhs(t, z, xi_ref=xi_ref):
            xi, x = z[:nh], z[nh:]
            v = mod.ashc_controller(xi, xi_ref)
            u = mod.ashc_interface(xi, x, v)
            f_bar, g, _ = plant_terms(x)
            return np.r_[mod.ashc_abstract_rhs(xi, v), f_bar[:, 0] + g @ u]

        sol = sint.solve_ivp(rhs, (t0, t1), z, t_eval=sample_times(t0, t1, SAMPLE_DT), **TRACKING_TOL)
        assert sol.status == 0, sol.message
        keep = slice(None) if not ts else slice(1, None)
        ts.append(sol.t[keep])
        zs.append(sol.y[:, keep])
        z, t0, k = sol.y[:, -1], t1, k + 1
    Z = np.concatenate(zs, axis=1)
    psi = np.stack([mod.ashc_kappa(Z[:nh, j]) for j in range(Z.shape[1])], axis=1)
    y = np.stack([plant_terms(Z[nh:, j])[2][:, 0] for j in range(Z.shape[1])], axis=1)
    err = float(np.linalg.norm(psi - y, axis=0).max())
    sim = arts["simulate"].values
    assert np.array_equal(np.concatenate(ts), sim["tracking/t"])
    # Both runs hold every step to rtol = atol = 1e-9 (simulate's also integrates the comparison state w,
    # so its steps differ): the maxima agree to a few hundred times that.
    assert err == pytest.approx(float(sim["tracking/max_abs_error"]), rel=1e-7, abs=1e-9)


# --- refusals ---------------------------------------------------------------------------------------------


def test_export_refuses_what_it_cannot_do(designs, tmp_path):
    d = designs["cuk_converter"]
    with pytest.raises(SpecError, match="--lang"):
        export_sources(d["spec"], d["arts"], "fortran")
    with pytest.raises(SpecError, match=r"does not end in \.c"):
        write_export(d["spec"], d["arts"], "c", tmp_path / "design.py")
    with pytest.raises(SpecError, match="importable"):
        write_export(d["spec"], d["arts"], "python", tmp_path / "my-design.py")
    # Artefacts of another plant (an edited decay rate changes what stabilise read) are refused, naming the stage;
    # a scenario's gain is no key of the design (issue 39: each stage follows the keys it reads).
    require_current(load_spec(edited(CUK, tmp_path, ("gain: 80.0", "gain: 81.0"), name="gain.yaml")), d["arts"])
    other = load_spec(edited(CUK, tmp_path, ("decay_rate: 2.0", "decay_rate: 1.9")))
    with pytest.raises(ArtefactError, match="stabilise.h5: was made from another spec"):
        require_current(other, d["arts"])
    with pytest.raises(ArtefactError, match="another spec"):
        write_export(other, d["arts"], "c", tmp_path / "design.c")
    assert not (tmp_path / "design.c").exists()
    # A missing stage is named.
    with pytest.raises(ArtefactError, match="no bound.h5 artefact"):
        gather(d["spec"], {k: a for k, a in d["arts"].items() if k != "bound"})


def test_python_and_c_sources_from_one_gathering(designs):
    # c_sources and python_source are pure functions of the gathered design.
    d = designs["unstable_linear"]
    design = gather(d["spec"], d["arts"])
    source, header = c_sources(design, "x.h")
    assert "static const double K[ASHC_N_INPUTS][ASHC_N_STATES]" in source and "feedback_of(&K[0][0]" in source
    # the law is the compiled loops' own function, printed: its arithmetic, with K's extents
    assert "s += (K[j * K_cols + i] * (x[i] - pm[i]));" in source
    assert "K = numpy.array(" in python_source(design)
    assert design.K is not None and design.K.shape == (1, 2)
    cuk = gather(designs["cuk_converter"]["spec"], designs["cuk_converter"]["arts"])
    assert cuk.K is None and "identity feedback" in c_sources(cuk)[0]


@needs_cc
def test_c_pseudo_inverse_matches_numpy(tmp_path):
    # The C file's fixed-size pseudo-inverse (one-sided Jacobi SVD) against numpy.linalg.pinv, for tall, wide,
    # square and rank-deficient matrices up to 5 x 5 (the designs above use it on 2 x 2 and 3 x 2 only).
    from ashc_cli.outputs.printers import _c_pinv_small

    source = tmp_path / "pinv.c"
    source.write_text("#include <math.h>\n" + "\n".join(_c_pinv_small(25, 5)) +
                      "\nvoid pinv(int rows, int cols, const double *a, double *out) { pinv_small(rows, cols, a, out); }\n")
    lib = tmp_path / "pinv.so"
    proc = subprocess.run([CC, *CFLAGS, "-Wextra", "-pedantic", "-shared", "-fPIC", "-o", str(lib), str(source), "-lm"], capture_output=True, text=True)
    assert proc.returncode == 0, proc.stderr
    pinv = ctypes.CDLL(str(lib)).pinv
    pinv.restype = None
    pinv.argtypes = [ctypes.c_int, ctypes.c_int, _P, _P]
    rng = np.random.default_rng(6)
    worst, deficient = 0.0, 0
    for k in range(600):
        rows, cols = (int(s) for s in rng.integers(1, 6, 2))
        a = rng.normal(size=(rows, cols)) * 10 ** rng.uniform(-3, 3)
        if k % 3 == 0 and min(rows, cols) > 1:   # exactly rank-deficient: a column (or row) of zeros, or a repeated one
            if k % 2:
                a[:, 0] = 0.0
            else:
                a[1, :] = a[0, :]
        s = np.linalg.svd(a, compute_uv=False)
        if s[0] / s[s > 1e-12 * s[0]].min() > 1e3:
            continue   # ill-conditioned: both sides lose cond x eps, no 1e-12 comparison to make
        a = np.ascontiguousarray(a)
        got = np.empty((cols, rows))
        pinv(rows, cols, _ptr(a), _ptr(got))
        want = np.linalg.pinv(a)
        worst = max(worst, float(np.abs(got - want).max() / np.abs(want).max()))
        deficient += int(np.linalg.matrix_rank(a) < min(rows, cols))
    assert deficient > 50
    assert worst <= RTOL


@pytest.mark.slow
@needs_cc
def test_cli_export_and_eval_u_w_agree(cli_run, tmp_path):
    """A user's check of exported code: `ashc export` writes FILE.c/.h; the compiled ashc_interface gives what
    `ashc eval DIR u_w` prints at the same point."""
    from .conftest import ashc

    out = cli_run["out"]
    proc = ashc("export", str(CUK), "--out", str(out), "--output", str(tmp_path / "cuk.c"), "--frozen", "--json")
    assert proc.returncode == 0, proc.stderr
    files = json.loads(proc.stdout)["files"]
    assert [Path(f).name for f in files] == ["cuk.c", "cuk.h"]
    # without --output the code goes beside the design's artefacts (not into the folder ashc was run from)
    default = ashc("export", str(CUK), "--out", str(out), "--lang", "python", "--frozen", "--json")
    assert default.returncode == 0, default.stderr
    assert json.loads(default.stdout)["files"] == [str(out / "cuk_converter_design.py")] and (out / "cuk_converter_design.py").exists()
    lib = CDesign(Path(files[0]), (4, 1, 1, 1, 1))
    rng = np.random.default_rng(3)
    for _ in range(5):
        xi, x, v = rng.uniform(0.1, 0.9, 1), rng.uniform(-20, 20, 4), rng.uniform(-50, 50, 1)
        at = ",".join([f"xi={float(xi[0])!r}"] + [f"x{i + 1}={float(x[i])!r}" for i in range(4)] + [f"v={float(v[0])!r}"])
        ev = ashc("eval", str(out), "u_w", "--spec", str(CUK), "--at", at, "--json")
        assert ev.returncode == 0, ev.stderr
        assert lib.interface(xi, x, v) == pytest.approx(json.loads(ev.stdout)["value"], rel=1e-12, abs=1e-15)
    # u_w needs the spec; a missing one is a clear one-line error.
    bad = ashc("eval", str(out), "u_w", "--at", "xi=0.5,x1=0,x2=0,x3=0,x4=0,v=0")
    assert bad.returncode == 2 and "--spec" in bad.stderr and "Traceback" not in bad.stderr
