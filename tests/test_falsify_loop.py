"""Tests of ashc_cli.closedloop.falsify_loop: falsify's runs as compiled code, one adaptive integration per run.

The reference is falsify._simulate, the numpy batch.  Integrated as a batch of one run, its step control is
that run's alone, so each compiled run must reproduce it to round-off: the same held inputs (greedy choices,
guard reversals), the same ratio, time of the worst ratio and states at every hold.
"""

import numpy as np
import pytest

from ashc_cli.products import falsify as F
from ashc_cli.closedloop.compiled import Unsupported
from ashc_cli.closedloop.falsify_loop import falsify_loop, layout
from ashc_cli.design.pipeline import DESIGN, design_model, run
from ashc_cli.problem.spec import load_spec

from .conftest import CUK, SPECS
from .test_falsify import COUNTER_SATURATION

try:
    import numba  # noqa: F401
except ImportError:   # pragma: no cover - numba is a dependency
    pytest.skip("numba is not installed", allow_module_level=True)


def _setting(spec_path, out, runs: int, t_final: float):
    spec = load_spec(spec_path)
    arts = run(spec, out, DESIGN)
    model = design_model(spec, arts)
    with np.errstate(all="ignore"):
        st = F._setup(model, arts, t_final)
        disc = F._discrete(st, st.lin)
        batch = F._first_batch(st, F._allocate(runs), np.random.default_rng(1), st.lin, disc)
    return st, batch


def _compiled(st, batch, tol=F.TOL, record=True):
    with np.errstate(all="ignore"):
        return st.loop.run(st, batch, tol, F._unit_candidates(st.model.m_hat), F._w0(st, batch), F.DIVERGED, F.GUARD_LOOKAHEAD, record)


# Cuk: one input, least-squares q, clipping; the counter-example: two inputs clipped channel by channel;
# bilinear_two_input: saturate: scale, a g that depends on x; unstable_linear: a feedback gain K and a
# certified region (the guard and the W0 boundary).
CASES = [CUK, COUNTER_SATURATION, SPECS / "bilinear_two_input.yaml", SPECS / "unstable_linear.yaml"]


@pytest.mark.parametrize("spec", CASES, ids=lambda p: p.stem)
def test_each_run_is_the_numpy_run_integrated_alone(spec, tmp_path):
    st, batch = _setting(spec, tmp_path, runs=11, t_final=1.0)
    assert st.loop is not None
    assert {"random", "greedy", "square", "linearised", "off_manifold"} <= set(batch.strategy)
    res = _compiled(st, batch)
    for i in range(len(batch)):
        with np.errstate(all="ignore"):
            ref = F._simulate(st, batch.take([i]), F.TOL, record=True)
        what = f"run {i} ({batch.strategy[i]})"
        assert res["k_at"][i] == ref["k_at"][0], what
        for key in ("left_V", "diverged", "forced"):
            assert res[key][i] == ref[key][0], (what, key)
        for key in ("ratio", "ratio_late", "max_error", "vsup", "at_limit"):
            assert res[key][i] == pytest.approx(ref[key][0], rel=1e-9, abs=1e-12), (what, key)
        np.testing.assert_allclose(res["vused"][i], ref["vused"][0], rtol=1e-9, atol=1e-12 * st.v_limit, err_msg=what)
        np.testing.assert_allclose(res["Z"][i], ref["Z"][0], rtol=1e-8, atol=1e-10 * st.scale.max(), err_msg=what)
        np.testing.assert_allclose(res["bound"][i], ref["bound"][0], rtol=1e-9, err_msg=what)


def test_results_do_not_depend_on_threads_or_pieces(tmp_path):
    st, batch = _setting(CUK, tmp_path, runs=11, t_final=1.0)
    st.loop.threads = 1
    a = _compiled(st, batch, record=False)
    st.loop.threads = 2
    b = st.loop.run(st, batch, F.TOL, F._unit_candidates(1), F._w0(st, batch), F.DIVERGED, F.GUARD_LOOKAHEAD, chunk=1)
    for key in ("ratio", "ratio_late", "k_at", "max_error", "vused", "steps"):
        np.testing.assert_array_equal(a[key], b[key], err_msg=key)


def test_progress_reports_every_run(tmp_path):
    st, batch = _setting(CUK, tmp_path, runs=11, t_final=0.5)
    seen = []
    st.loop.run(st, batch, F.TOL, F._unit_candidates(1), F._w0(st, batch), F.DIVERGED, F.GUARD_LOOKAHEAD,
                progress=lambda done, total, seconds: seen.append((done, total)), chunk=3)
    assert [d for d, _ in seen] == sorted(d for d, _ in seen)
    assert seen[-1] == (len(batch), len(batch))


def test_layout_has_room_for_every_term():
    off = layout(nh=2, n=5, m=3, mh=2, p=2)
    a_size, b_size, w_size = off[-3:]
    assert a_size == 2 + 4 + 3 + 10 + 2 + 5 + 10          # phi, delta, l, dpd, kappa, p, dp/dxi
    assert b_size == 5 + 15 + 2 + 10                      # f_bar, g, h, dh/dx
    assert w_size == 3 + 6 + 15 + 10 + 15 + 4 + 3 + 2     # kx, q, L^T g, L^T dpd, pinv, delta^+, corr, v_in
    assert off[0] == 0 and off[7] == 0 and off[11] == 0 and np.all(np.diff(off[:7]) > 0)


def test_without_numba_the_numpy_batch_runs(tmp_path, monkeypatch):
    """ASHC_COMPILED=0: no compiled loop; the search runs on the numpy batch and says so in the artefact."""
    spec = load_spec(CUK)
    arts = run(spec, tmp_path, DESIGN)
    monkeypatch.setenv("ASHC_COMPILED", "0")
    with pytest.raises(Unsupported):
        falsify_loop(design_model(spec, arts), arts, np.eye(4), np.eye(4), np.zeros((1, 4)))
    art = F.falsify(design_model(spec, arts), arts, runs=6, seed=0, t_final=1.0)
    assert art.meta["engine"].startswith("numpy")
    monkeypatch.setenv("ASHC_COMPILED", "1")
    fast = F.falsify(design_model(spec, arts), arts, runs=6, seed=0, t_final=1.0)
    assert fast.meta["engine"].startswith("compiled")
    # The batch's step is set by its worst run, the compiled one per run: the same runs, within the tolerance.
    assert fast.values["max_ratio"] == pytest.approx(art.values["max_ratio"], rel=1e-4)
    np.testing.assert_allclose(fast.values["run_ratio"], art.values["run_ratio"], rtol=1e-3, atol=1e-6)


def test_a_run_alone_is_the_run_in_its_batch(tmp_path):
    """What lets the search keep no inputs: the verification integrates a run again alone (falsify._replay)."""
    st, batch = _setting(COUNTER_SATURATION, tmp_path, runs=11, t_final=1.0)
    res = _compiled(st, batch, record=False)
    for i in range(len(batch)):
        alone = _compiled(st, batch.take([i]), record=False)
        np.testing.assert_array_equal(alone["vused"][0], res["vused"][i])
        assert alone["ratio"][0] == res["ratio"][i]


def test_compiled_search_breaks_a_planted_bound_on_the_manifold(tmp_path):
    """A fresh counter-example for the compiled engine: on the quarter car (ill-conditioned M, where the search
    on the manifold reaches 0.45 of the certified gain) a gain of 0.4 G is unsound, and the search must say so
    with W0 = 0, where only G ||v|| counts."""
    import dataclasses

    spec = load_spec(SPECS / "quarter_car.yaml")
    arts = run(spec, tmp_path, DESIGN)
    bound = arts["bound"]
    planted = dataclasses.replace(bound, values={**bound.values, "gain": 0.4 * bound.values["gain"]})
    art = F.falsify(design_model(spec, arts), {**arts, "bound": planted}, runs=60, seed=0, t_final=2.0)
    assert art.meta["engine"].startswith("compiled")
    assert art.values["max_ratio_w0_zero"] > 1.0
    assert not art.checks["falsify_ratio"].passed
