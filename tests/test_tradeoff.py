"""Tests of ashc_cli.products.tradeoff: time to reach the reference levels against the guaranteed tolerance (docs/guaranteed.md)."""

import numpy as np
import pytest

from ashc_cli.products import tradeoff
from ashc_cli.design.artefacts import read_artefact
from ashc_cli.errors import SpecError
from ashc_cli.problem.spec import load_spec
from ashc_cli.design.stages import simulate

from .conftest import ROOT, edited

GUARANTEED = ROOT / "tests" / "specs" / "cuk_guaranteed.yaml"
#: The Cuk spec cut to three near levels and a 5 s dwell, so that both modes reach them quickly.
SHORT = (("reference_levels: [-19.11, -80.90, -44.27, -4.31, -12.48, -32.91]", "reference_levels: [-19.11, -44.27, -12.48]"),
         ("dwell: 20.0", "dwell: 5.0"), ("t_final: 120.0", "t_final: 15.0"))


@pytest.fixture(scope="module")
def short_spec(tmp_path_factory):
    return edited(GUARANTEED, tmp_path_factory.mktemp("tradeoff_spec"), *SHORT, name="cuk_short.yaml")


@pytest.fixture(scope="module")
def result(short_spec, tmp_path_factory):
    out = tmp_path_factory.mktemp("tradeoff")
    arts, art, figure = tradeoff.run_tradeoff(load_spec(short_spec), out, [20.0, 10.0])
    return {"arts": arts, "art": art, "figure": figure, "out": out}


def test_parse_tolerances():
    assert tradeoff.parse_tolerances("1,2,5,10,20") == [1.0, 2.0, 5.0, 10.0, 20.0]
    assert tradeoff.parse_tolerances(" 0.5 ") == [0.5]
    for text, fragment in (("", "is empty"), ("1,x", "'x' is not a number"), ("1,-2", "-2 is not a positive"), ("1,inf", "inf is not a positive"),
                           ("1,1", "1 is given twice")):
        with pytest.raises(SpecError) as err:
            tradeoff.parse_tolerances(text)
        assert err.value.where == "--tolerances" and fragment in err.value.line() and err.value.exit_code == 2


def test_artefact_is_written_and_holds_both_modes(result, short_spec):
    art, out = result["art"], result["out"]
    stored = read_artefact(out / "tradeoff.h5")
    assert stored.stage == "tradeoff" and stored.provenance["spec_sha256"] == load_spec(short_spec).sha256
    v = stored.values
    assert list(v["tolerances"]) == [20.0, 10.0]
    assert np.asarray(v["levels"]).shape == (3, 1)
    for mode in tradeoff.MODES:
        assert np.asarray(v[f"reach_time/{mode}"]).shape == (2, 3)
        assert list(v[f"refusal/{mode}"]) == ["", ""]
        assert np.allclose(v[f"total_time/{mode}"], np.asarray(v[f"reach_time/{mode}"]).sum(axis=1))
    G = float(result["arts"]["bound"].value("gain"))
    assert np.allclose(v["budget_v_max"], np.array([20.0, 10.0]) / G, rtol=1e-12)        # W0 = 0: EPS / G
    assert np.allclose(v["proved_tolerance/budget"], [20.0, 10.0]) and np.allclose(v["proved_tolerance/governor"], [20.0, 10.0])
    assert set(stored.provenance["upstream"]) == set(tradeoff.UPSTREAM)
    # both modes run compiled (the governor in ashc_cli/closedloop/governor.py), unless numba is switched off
    from ashc_cli.closedloop.compiled import available
    expected = "ashc_cli.closedloop.compiled (numba)" if available() else "scipy.integrate.solve_ivp"
    assert art.meta["implementation"] == {"setpoint": expected, "governor": expected}


def test_governor_is_faster_and_both_slow_down_with_a_tighter_tolerance(result):
    v = result["art"].values
    bud, gov = np.asarray(v["reach_time/budget"]), np.asarray(v["reach_time/governor"])
    assert np.all(np.isfinite(bud)) and np.all(np.isfinite(gov))      # every level reached by both, at both tolerances
    assert np.all(bud[:, 0] == 0) and np.all(gov[:, 0] == 0)           # the first level is the start's output
    assert np.all(bud[:, 1:] > 0) and np.all(gov[:, 1:] > 0)
    # Halving the tolerance halves the allowed v in both modes: both take longer (about twice).
    assert np.all(bud[1, 1:] > 1.5 * bud[0, 1:]) and np.all(gov[1, 1:] > 1.5 * gov[0, 1:])
    speedup = np.asarray(v["speedup"])[:, 1:]
    assert np.all(speedup >= 2.0)
    assert np.allclose(speedup, bud[:, 1:] / gov[:, 1:])


def test_reach_times_match_the_simulate_run(result, short_spec, tmp_path):
    # The governor's reach-time run and the scenario run of `ashc simulate` start each level from the same settled
    # state, so they must agree (to the coarser sampling of the reach-time run, 5e-4 dwell = 2.5 ms).
    from ashc_cli.design.pipeline import run
    spec = load_spec(edited(short_spec, tmp_path, ("tolerance: 5.0", "tolerance: 10.0"), name="eps10.yaml"))
    sim = run(spec, tmp_path / "out", ("simulate",))["simulate"].values
    gov = np.asarray(result["art"].values["reach_time/governor"])[1]
    assert sim["tracking/level_reached_within_tolerance_time"] == pytest.approx(gov, abs=2.5e-3 + 1e-9)
    assert sim["tracking/budget_reach_time"] == pytest.approx(np.asarray(result["art"].values["reach_time/budget"])[1], abs=1e-9)


def test_table_has_one_row_per_tolerance_and_mode(result):
    rows = tradeoff.table(result["art"])
    assert rows[0].split()[:2] == ["EPS", "mode"] and rows[0].split()[2:5] == ["-19.11", "-44.27", "-12.48"]
    assert rows[1] == "seconds to reach each level within EPS and their total; levels and EPS in the output units"
    assert [r.split()[:2] for r in rows[2:]] == [["20", "budget"], ["20", "governor"], ["10", "budget"], ["10", "governor"]]
    assert rows[3].rstrip().endswith("x") and not rows[2].rstrip().endswith("x")   # the speed-up on the governor's row
    assert tradeoff.table(result["art"], unit="V")[1].endswith("levels and EPS in V")


def test_frontier_figure_is_one_column_wide(result):
    from PIL import Image
    figure = result["figure"]
    assert figure == result["out"] / "plots" / "tradeoff.png" and figure.exists()
    with Image.open(figure) as image:
        assert image.size[0] == round(3.5 * 200)       # 3.5 in at 200 dpi, as ashc_cli/outputs/plots.py draws


def test_a_tolerance_the_start_cannot_meet_is_refused_per_mode(result, short_spec, tmp_path):
    # Same design, x0 off the manifold with sqrt(W0 / alpha_h) = 15 V: 10 V is refused by both modes, 20 V is not.
    from ashc_cli.design.pipeline import design_model
    arts = result["arts"]
    M = np.asarray(arts["stabilise"].value("M"))
    alpha_h = float(arts["bound"].value("alpha_h"))
    spec0 = load_spec(short_spec)
    plant = simulate.DesignTerms(design_model(spec0, arts), arts)
    p0 = plant.p_map(0.6156)[:, 0]
    shift = 15.0 * np.sqrt(alpha_h / M[3, 3])                       # along x4 alone: W0 = shift^2 M44
    x0 = p0 + np.array([0, 0, 0, shift])
    spec = load_spec(edited(short_spec, tmp_path, ("x0: on_manifold", f"x0: [{', '.join(repr(float(c)) for c in x0)}]"), name="off.yaml"))
    art = tradeoff.tradeoff(design_model(spec, arts), arts, [10.0, 20.0], horizon_dwells=400)
    v = art.values
    assert v["W0"] == pytest.approx(15.0**2 * alpha_h, rel=1e-9)
    for mode in tradeoff.MODES:
        assert "cannot be guaranteed" in v[f"refusal/{mode}"][0] and v[f"refusal/{mode}"][1] == ""
        assert np.all(np.isnan(np.asarray(v[f"reach_time/{mode}"])[0]))
    assert v["proved_tolerance/budget"][1] == pytest.approx(20.0, rel=1e-12)
    assert "refused: simulate.tracking.abstract_controller.tolerance" not in "\n".join(tradeoff.table(art))
    assert "refused: 10 cannot be guaranteed" in "\n".join(tradeoff.table(art))
