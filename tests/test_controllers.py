"""A controller added from this file, as docs/guide.md ("Adding a controller") says: one law, registered, then run by
the tracking runner that simulate uses and printed by ashc export (C and Python)."""

from __future__ import annotations

import ctypes
import subprocess

import numpy as np
import pytest
from numba import njit

from ashc_cli.closedloop import controllers
from ashc_cli.closedloop.controllers import Controller, register
from ashc_cli.closedloop.laws import F1, F2, LAW_SIGNATURE
from ashc_cli.closedloop.plan import Law
from ashc_cli.closedloop.runner import SAMPLE_DT, closed_loop_run, tracking_loop_for, tracking_segments
from ashc_cli.closedloop.terms import DesignTerms
from ashc_cli.design.pipeline import design_model
from ashc_cli.errors import DesignError
from ashc_cli.outputs.export_design import gather
from ashc_cli.outputs.printers import c_sources, python_source

from .test_export import CC, CFLAGS, needs_cc


# --- the guide's example, step 1: the law (numba, the law signature, in the subset ashc export prints) -------------

@njit(LAW_SIGNATURE, cache=True)
def proportional(t: float, z: F1, ref: F1, phi: F1, delta: F2, prm: F1, v: F1):
    """v = clip(k (xi_ref - xi), -v_max, v_max) on each abstract input (n_hat = m_hat), prm = [k, v_max]."""
    for a in range(v.size):
        v[a] = min(max(prm[0] * (ref[a] - z[a]), -prm[1]), prm[1])


# --- step 2: registered under a name, its parameters taken from the run's Law -------------------------------------

PROPORTIONAL = register(Controller("proportional", lambda model: proportional, lambda law: np.array([law.gain, law.v_max]),
                                   "v = clip(k (xi_ref - xi), -v_max, v_max)", printed=proportional))


def _numpy_law(xi, ref, k, v_max):
    return np.clip(k * (np.asarray(ref) - np.asarray(xi)), -v_max, v_max)


@pytest.fixture(scope="module")
def cuk(paper_spec, paper_design):
    model = design_model(paper_spec, paper_design)
    return model, DesignTerms(model, paper_design), paper_design


def test_a_registered_controller_runs_in_the_tracking_runner(cuk):
    model, plant, arts = cuk
    loop = tracking_loop_for(model, arts, Law("proportional", 40.0, 5.0))
    refs = [np.array([model.V[0].mean() + 0.2 * np.ptp(model.V[0])]), np.array([model.V[0].mean() - 0.1 * np.ptp(model.V[0])])]
    xi0 = np.array([model.V[0].mean()])
    z0 = np.r_[xi0, plant.p_map(*xi0)[:, 0], 0.0]
    segments = tracking_segments(0.02, 0.01, 2, SAMPLE_DT / 10)
    k, v_max = 40.0, 5.0
    run = closed_loop_run(model, plant, arts, Law("proportional", k, v_max), z0, segments, refs, loop)
    # at every sample v is the registered law of the sampled xi and its segment's reference, nothing else
    want = np.stack([_numpy_law(run["xi"][:, i], refs[run["reference_index"][i]], k, v_max) for i in range(run["t"].size)], axis=1)
    np.testing.assert_allclose(run["v"], want, rtol=1e-12, atol=1e-12)
    assert np.any(np.abs(want) >= v_max) and np.any(np.abs(want) < v_max)      # clipped and not
    # and xi' = phi_bar + delta v with that v: xi heads for each reference
    assert abs(run["xi"][0, run["reference_index"] == 0][-1] - refs[0][0]) < abs(xi0[0] - refs[0][0])
    # the set-point law gives another run from the same start: the law is what the runner ran
    other = closed_loop_run(model, plant, arts, Law("setpoint", k, v_max), z0, segments, refs, loop)
    assert not np.allclose(other["v"], run["v"])


def test_an_unknown_controller_is_refused_naming_the_registered_ones(cuk):
    with pytest.raises(DesignError) as err:
        controllers.controller("pid")
    assert "'pid'" in str(err.value) and "proportional" in str(err.value) and "setpoint" in str(err.value)


def test_a_registered_controller_is_exported_in_python(cuk, paper_spec, tmp_path):
    _, _, arts = cuk
    design = gather(paper_spec, arts)
    text = python_source(design, (PROPORTIONAL, [40.0, 5.0]))
    assert "def proportional(t, z, ref, phi, delta, prm, v):" in text
    space: dict = {}
    exec(compile(text, "exported.py", "exec"), space)        # the exported module, run as its user would
    rng = np.random.default_rng(0)
    for _ in range(50):
        xi, ref = rng.uniform(0.0, 1.0, 1), rng.uniform(0.0, 1.0, 1)
        np.testing.assert_array_equal(space["ashc_controller"](xi, ref), _numpy_law(xi, ref, 40.0, 5.0))


@needs_cc
def test_a_registered_controller_is_exported_in_c(cuk, paper_spec, tmp_path):
    _, _, arts = cuk
    source, header = c_sources(gather(paper_spec, arts), "toy.h", (PROPORTIONAL, [40.0, 5.0]))
    assert "static void proportional(double t, const double *z, int z_n" in source
    assert "v = clip(k (xi_ref - xi), -v_max, v_max): the abstract controller proportional" in header
    (tmp_path / "toy.c").write_text(source)
    (tmp_path / "toy.h").write_text(header)
    lib = tmp_path / "toy.so"
    proc = subprocess.run([CC, *CFLAGS, "-Wextra", "-pedantic", "-shared", "-fPIC", "-o", str(lib), str(tmp_path / "toy.c"), "-lm"],
                          capture_output=True, text=True)
    assert proc.returncode == 0, proc.stderr
    so = ctypes.CDLL(str(lib))
    P = ctypes.POINTER(ctypes.c_double)
    rng = np.random.default_rng(1)
    for _ in range(50):
        xi, ref, v = rng.uniform(0.0, 1.0, 1), rng.uniform(0.0, 1.0, 1), np.empty(1)
        so.ashc_controller(xi.ctypes.data_as(P), ref.ctypes.data_as(P), v.ctypes.data_as(P))
        np.testing.assert_array_equal(v, _numpy_law(xi, ref, 40.0, 5.0))
