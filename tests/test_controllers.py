"""A controller added from this file, as docs/guide.md ("Adding a controller") says: one law, registered, then run by
the tracking runner that simulate uses, by falsify's CONTROLLER runs and printed by ashc export (C and Python); and
named by a spec (``abstract_controller.kind: registered``), so that ``ashc simulate``, ``falsify`` and ``export``
run it from the command line (in this process, where the test file registered it)."""

from __future__ import annotations

import ctypes
import dataclasses
import shutil
import subprocess

import numpy as np
import pytest
from numba import njit

from ashc_cli.cli.common import main
from ashc_cli.closedloop import controllers, falsify_core
from ashc_cli.closedloop.controllers import Controller, register
from ashc_cli.closedloop.laws import F1, F2, LAW_SIGNATURE
from ashc_cli.closedloop.plan import Law
from ashc_cli.closedloop.runner import SAMPLE_DT, closed_loop_run, tracking_loop_for, tracking_segments
from ashc_cli.closedloop.terms import DesignTerms
from ashc_cli.design.artefacts import read_artefact
from ashc_cli.design.pipeline import DESIGN, design_model, run
from ashc_cli.errors import DesignError
from ashc_cli.problem.spec import load_spec
from ashc_cli.products import falsify as F, falsify_linear, strategies as ST
from ashc_cli.outputs.export_design import gather
from ashc_cli.outputs.printers import c_sources, python_source

from .conftest import CUK_PAPER_M, edited
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


# --- step 3: named by a spec, run by the commands ------------------------------------------------------------------

def _toy_spec(tmp_path, paper_out):
    """The paper's Cuk spec closing its tracking run with the registered law, and a copy of its design."""
    spec = edited(CUK_PAPER_M, tmp_path, ("{kind: setpoint, gain: 80.0, v_max: 60.0}", "{kind: registered, name: proportional, gain: 40.0, v_max: 5.0}"),
                  ("t_final: 30.0", "t_final: 6.0"), name="toy.yaml")
    out = tmp_path / "out"
    shutil.copytree(paper_out, out)
    return spec, out


def _ashc(*args) -> int:
    """``ashc ARGS`` in this process (the registration above is this process's)."""
    try:
        main([str(a) for a in args])
    except SystemExit as exc:
        return int(exc.code or 0)
    return 0


def test_the_commands_run_the_controller_a_spec_names(tmp_path, paper_out, capsys):
    spec, out = _toy_spec(tmp_path, paper_out)
    assert _ashc("simulate", spec, "--out", out) == 0
    sim = read_artefact(out / "simulate.h5").values
    xi, v, idx = (np.asarray(sim[f"tracking/{k}"]) for k in ("xi", "v", "reference_index"))
    refs = np.asarray(sim["tracking/xi_ref"])
    want = np.stack([_numpy_law(xi[:, i], refs[:, i], 40.0, 5.0) for i in range(xi.shape[1])], axis=1)
    np.testing.assert_allclose(v, want, rtol=1e-12, atol=1e-12)         # simulate ran the registered law
    assert set(np.unique(idx)) == {0, 1} and np.any(np.abs(want) >= 5.0) and np.any(np.abs(want) < 5.0)

    assert _ashc("falsify", spec, "--out", out, "--runs", "32", "--t-final", "1") == 0
    fals = read_artefact(out / "falsify.h5")
    strategy = np.asarray(fals.values["strategy"]).astype(str)
    assert fals.meta["runs_per_strategy"]["controller"] == np.sum(strategy == "controller") > 0
    assert np.all(np.asarray(fals.values["run_ratio"])[strategy == "controller"] <= 1.0)

    assert _ashc("export", spec, "--out", out, "--lang", "python", "--output", tmp_path / "toy_design.py") == 0
    space: dict = {}
    exec(compile((tmp_path / "toy_design.py").read_text(), "toy_design.py", "exec"), space)
    for xi0, ref in ((0.2, 0.9), (0.5, 0.45), (0.9, -1.0)):
        np.testing.assert_array_equal(space["ashc_controller"](np.array([xi0]), np.array([ref])), _numpy_law([xi0], [ref], 40.0, 5.0))


def test_falsify_runs_the_registered_law_as_it_is(tmp_path, paper_out):
    # the CONTROLLER runs' v at every hold boundary is the registered law of (xi, the segment's reference), its
    # norm clipped to v_limit, and nothing else (no noise, no guard)
    spec, out = _toy_spec(tmp_path, paper_out)
    arts = run(load_spec(spec), out, DESIGN)
    with np.errstate(all="ignore"):
        st = F._setup(design_model(load_spec(spec), arts), arts, 1.0)
        batch = ST._first_batch(st, ST._allocate(24), np.random.default_rng(3), st.lin, falsify_linear.discrete(st, st.lin))
        own = np.flatnonzero(batch.mode == falsify_core.CONTROLLER)
        b = batch.take(own)
        res = st.loop.run(st, b, F.TOL, ST.unit_candidates(1), ST.w0(st, b), ST.DIVERGED, ST.GUARD_LOOKAHEAD, True)
    assert own.size > 0 and not np.any(b.guard) and not np.any(b.noise)
    H, S = st.holds, b.refs.shape[0]
    for r in range(own.size):
        for k in range(H):
            ref = b.refs[min(k * S // H, S - 1), r]
            want = _numpy_law(res["Z"][r, k, :1], ref, 40.0, 5.0)
            want = want * min(1.0, st.v_limit / max(np.linalg.norm(want), 1e-300))
            np.testing.assert_allclose(res["v"][r, k], want, rtol=1e-13, atol=1e-13)
    with pytest.raises(ValueError, match="CONTROLLER"):        # such runs without the law: refused, not run with another
        st.loop.run(dataclasses.replace(st, controller=None), b, F.TOL, ST.unit_candidates(1), ST.w0(st, b), ST.DIVERGED, ST.GUARD_LOOKAHEAD)


def test_a_spec_naming_an_unregistered_controller_is_refused_in_one_line(tmp_path, paper_out, capsys):
    spec = edited(CUK_PAPER_M, tmp_path, ("{kind: setpoint, gain: 80.0, v_max: 60.0}", "{kind: registered, name: pid, v_max: 5.0}"))
    out = tmp_path / "out"
    shutil.copytree(paper_out, out)
    assert _ashc("simulate", spec, "--out", out) != 0
    err = capsys.readouterr().err.strip().splitlines()      # the design's stage lines (up to date), then one error line
    assert err[-1].startswith("error: simulate.tracking.abstract_controller.name: 'pid'") and "proportional" in err[-1], err
    assert not any("Traceback" in line for line in err)
    assert not (out / "simulate.h5").exists()


def test_the_names_of_the_spec_kinds_are_not_registrable():
    with pytest.raises(DesignError, match="guaranteed"):
        register(Controller("guaranteed", lambda model: proportional, lambda law: np.zeros(0), "no"))


def test_a_controller_from_an_installed_package_is_found_by_its_entry_point(monkeypatch):
    # a package declares [project.entry-points."ashc.controllers"] toy = "pkg:CONTROLLER"; the first spec naming an
    # unregistered controller loads them
    import importlib.metadata as md

    plugin = Controller("plugged", lambda model: proportional, lambda law: np.array([law.gain, law.v_max]), "v = the plugin's")
    ep = md.EntryPoint("plugged", "toy_pkg:CONTROLLER", controllers.ENTRY_POINTS)
    monkeypatch.setattr(md.EntryPoint, "load", lambda self: plugin)
    monkeypatch.setattr(md, "entry_points", lambda group=None: [ep] if group == controllers.ENTRY_POINTS else [])
    monkeypatch.delitem(controllers.REGISTRY, "plugged", raising=False)
    assert controllers.controller("plugged") is plugin
    monkeypatch.delitem(controllers.REGISTRY, "plugged")
