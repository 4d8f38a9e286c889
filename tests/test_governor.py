"""The compiled guaranteed governor (ashc_cli/closedloop/governor.py) against the scipy path's law
(tests/oracle.py: governor_scale, governor_law), which stays the reference."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from ashc_cli.closedloop import governor as gov
from ashc_cli.closedloop import plan as gplan
from ashc_cli.design.stages import simulate

from . import oracle as reference
from .oracle import TrackingOracle
from .test_simulate import _random_interface

GUARANTEED = Path(__file__).parent / "specs" / "cuk_guaranteed.yaml"
SAT = {False: 0, True: 1, "scale": 2}
PRM_TAIL = [np.inf, 0.0, 1.0, gplan.GOVERNOR_GRID, gplan.GOVERNOR_BISECTIONS, *gplan.GOVERNOR_BACKOFF]


def _prm():
    return np.array([0.0, 0.0, 0.0, 0.0, *PRM_TAIL], dtype=float)


@pytest.mark.parametrize("saturate", [True, False, "scale"])
@pytest.mark.parametrize("m", [1, 2, 3])
def test_compiled_scale_is_the_reference_scale(saturate, m):
    # the same s (to the round-off of a different summation order), the same admissibility, u(s) and r(s)
    rng = np.random.default_rng(7 + m + 10 * SAT[saturate])
    for _ in range(80):
        L, l, fb, qv, dv, g, U = _random_interface(rng, m, saturate)
        grid = np.linspace(0.0, 1.0, 201)
        _, _, q2 = reference.interface_r(grid, L, l, fb, qv, dv, g, U, saturate)
        bound = float(rng.uniform(0.05, 1.5) * np.median(q2)) + 1e-3
        s_ref, u_ref, r_ref, ok_ref = reference.governor_scale(L, l, fb, qv, dv, g, U, saturate, bound)
        u, r = np.empty(m), np.empty(dv.size)
        P = gov.Point(np.ascontiguousarray(L), l, fb, qv, dv, np.ascontiguousarray(g), np.ascontiguousarray(U), SAT[saturate], L.shape[0] - 1)
        s, ok = gov.governor_scale(P, bound, _prm(), u, r)
        assert ok == ok_ref
        assert s == pytest.approx(s_ref, abs=1e-9)
        assert np.allclose(u, u_ref, rtol=1e-9, atol=1e-9) and np.allclose(r, r_ref, rtol=1e-9, atol=1e-9)
        # and never an s that breaks the condition, evaluated through the compiled interface itself
        if ok:
            assert gov.interface_at(s, P, np.empty(m), np.empty(dv.size), np.empty(m)) <= bound


def test_breakpoints_are_the_reference_breakpoints():
    rng = np.random.default_rng(3)
    for saturate in (True, False, "scale"):
        for _ in range(50):
            L, l, fb, qv, dv, g, U = _random_interface(rng, 3, saturate)
            ends_ref, affine_ref = reference.breakpoints(l, fb, qv, U, saturate)
            ends = np.empty(7)
            count, affine = gov.breakpoints(gov.Point(np.eye(3), l, fb, qv, dv, np.zeros((3, 3)), U, SAT[saturate], 0), ends)
            assert affine == affine_ref and list(ends[:count]) == ends_ref


@pytest.fixture(scope="module")
def cuk(tmp_path_factory):
    from ashc_cli.closedloop.terms import DesignTerms
    from ashc_cli.design.pipeline import DESIGN, design_model, run
    from ashc_cli.problem.spec import load_spec
    spec = load_spec(GUARANTEED)
    arts = run(spec, tmp_path_factory.mktemp("cuk_governor"), DESIGN)
    model = design_model(spec, arts)
    return model, DesignTerms(model, arts), {k: arts[k] for k in simulate.UPSTREAM if k in arts}


def test_compiled_governor_run_is_the_scipy_run(cuk):
    # 3 s of the Cuk's guaranteed run from the step to the second level at t = 20 s (where the governor holds s < 1),
    # both paths from the same state (the first 20 s run compiled).
    model, plant, up = cuk
    tr, ctl = model.spec.simulate.tracking, model.spec.simulate.tracking.abstract_controller
    xi0, x0, W0, levels, refs = simulate.tracking_start(model, plant, up)
    lam, eps = float(up["bound"].value("lambda")), float(up["bound"].value("epsilon"))
    plan = gplan.guaranteed_plan(ctl.tolerance, ctl.mode, W0, up)
    law = plan.law("governor", ctl.gain, model.m_hat, float(up["bound"].values.get("v_max_certified", np.inf)), lam, eps)
    loop = simulate.tracking_loop_for(model, up, law)
    assert loop is not None
    first = simulate.closed_loop_run(model, plant, up, law, np.r_[xi0, x0, W0], simulate.tracking_segments(20.0, tr.dwell, 1), refs, loop)
    z0 = first["z_end"]
    segments = [(20.0, 23.0, simulate.sample_times(20.0, 23.0, simulate.SAMPLE_DT), 1)]
    mine = simulate.closed_loop_run(model, plant, up, law, z0, segments, refs, loop)
    ref = simulate.closed_loop_run(model, plant, up, law, z0, segments, refs, TrackingOracle(model, plant, up, law))
    assert mine["compiled"] and not ref["compiled"]
    assert np.array_equal(mine["t"], ref["t"])
    # measured: 1e-14 of the scale on x and y, 1e-13 on w and v, 1e-11 on the slack (the same steps on this window;
    # over the whole 120 s run the step sequences part at the governor's kinks, 2e-8 of the scale on x)
    for key in ("xi", "x", "y", "w", "v", "u", "scale"):
        scale = max(1.0, float(np.abs(ref[key]).max()))
        assert np.abs(mine[key] - ref[key]).max() <= 1e-10 * scale, key
    assert np.abs(mine["slack"] - ref["slack"]).max() <= 1e-8 * max(1.0, float(np.abs(ref["slack"]).max()))
    assert np.min(mine["scale"]) < 0.5                 # the governor did act in this window
    assert np.all(mine["slack"] >= 0.0) and np.all(mine["w"] <= plan.governor_level)
