"""Tests of the spec contract (ashc_cli.problem.spec)."""

import pytest

from ashc_cli.errors import SpecError
from ashc_cli.problem.spec import load_spec, parse_spec_text

from .conftest import CUK, CUK_PAPER_M


def cuk(*pairs):
    text = CUK.read_text()
    for old, new in pairs:
        assert old in text
        text = text.replace(old, new)
    return text


def error_of(text):
    with pytest.raises(SpecError) as err:
        parse_spec_text(text)
    assert err.value.exit_code == 2
    line = err.value.line()
    assert "\n" not in line
    return line


def test_example_specs_load():
    spec = load_spec(CUK)
    assert spec.name == "cuk_converter"
    assert spec.concrete.states == ["x1", "x2", "x3", "x4"]
    assert spec.stabilisability.decay_rate == 2.0
    assert load_spec(CUK_PAPER_M).stabilisability.M[0][0] == 0.4804


def test_sha_ignores_comments_but_not_values():
    a = parse_spec_text(cuk())
    b = parse_spec_text(cuk(("# duty cycle", "# the duty cycle d")))
    c = parse_spec_text(cuk(("E: 12.0", "E: 12.5")))
    assert a.sha256 == b.sha256 != c.sha256


def test_unknown_key_suggests_closest():
    line = error_of(cuk(("  delta: \"", "  detla: \"")))
    assert "abstract.detla" in line and "did you mean 'delta'" in line


def test_missing_key():
    assert "concrete.h: missing" in error_of(cuk(('  h: ["x4"]\n', "")))


@pytest.mark.parametrize(
    "pair, fragment",
    [
        (("\"x1/C_2\", ", ""), "concrete.f_bar: has 3 entries; expected 4"),
        (("[\"0\"]]", "[\"0\", \"1\"]]"), "concrete.g[3]: has 2 entries; expected 1"),
        (("input_bounds: [[0, 1]]", "input_bounds: [[1, 0]]"), "concrete.input_bounds[0]: lo = 1.0 > hi = 0.0"),
        (("output_set: [[-120, 0]]", "output_set: [[-120]]"), "concrete.output_set[0]"),
        (("states: [xi]", "states: [x1]"), "already used in concrete.states"),
        (("states: [xi]", "states: [sin]"), "reserved"),
        (("E: 12.0", "E: .nan"), "parameters.E"),
        (("method: polytopic_lmi", "method: lmi"), "stabilisability.method"),
        (("decay_rate: 2.0", "decay_rate: -2"), "stabilisability.decay_rate"),
        (("xi0: [0.6156]", "xi0: [0.6, 0.1]"), "simulate.tracking.xi0: has 2 entries"),
    ],
)
def test_bad_fields_named(pair, fragment):
    assert fragment in error_of(cuk(pair))


def test_method_given_needs_M():
    assert "stabilisability.M: missing" in error_of(cuk(("method: polytopic_lmi", "method: given")))


def test_yaml_problems():
    assert "malformed YAML" in error_of("name: [")
    assert "duplicate key 'name'" in error_of("name: a\nname: b\n")
    assert "aliases" in error_of("a: &x [1]\nb: *x\n")
    assert "top level is a list" in error_of("- 1\n")
    assert ": empty; expected a YAML mapping" in error_of("")


def test_file_errors(tmp_path):
    with pytest.raises(SpecError, match="no such file"):
        load_spec(tmp_path / "absent.yaml")
    with pytest.raises(SpecError, match="is a directory"):
        load_spec(tmp_path)


def test_unknown_key_that_is_not_a_name():
    # Found by `make fuzz`: a top-level key that is not an identifier used to crash the error formatter.
    assert "unknown key '0:'" in error_of("'0:': 1\n")
    assert "key 7 is not a name" in error_of("7: x\n")
    assert "is not a name" in error_of("name: a\nparameters: {1.5: 2}\n")


# --- bounds as a map keyed by name ------------------------------------------------------------------------

def test_bounds_as_maps_keyed_by_name_equal_the_lists():
    listed = parse_spec_text(cuk())
    mapped = parse_spec_text(cuk(("input_bounds: [[0, 1]]", "input_bounds: {u: [0, 1]}"), ("output_set: [[-120, 0]]", "output_set: {y1: [-120, 0]}")))
    assert mapped.concrete.input_bounds == listed.concrete.input_bounds == [[0.0, 1.0]]
    assert mapped.concrete.output_set == listed.concrete.output_set == [[-120.0, 0.0]]
    assert mapped.sha256 == listed.sha256          # the same spec: both forms hash alike


def test_bounds_map_follows_the_declared_order_not_the_written_one():
    from .conftest import SPECS
    text = (SPECS / "linear_left_inverse.yaml").read_text()
    spec = parse_spec_text(text.replace("input_bounds: {u1: [-3, 3], u2: [-3, 3]}", "input_bounds: {u2: [-2, 1], u1: [-3, 3]}"))
    assert spec.concrete.inputs == ["u1", "u2"] and spec.concrete.input_bounds == [[-3.0, 3.0], [-2.0, 1.0]]


@pytest.mark.parametrize("pair, fragment", [
    (("input_bounds: [[0, 1]]", "input_bounds: {w: [0, 1]}"),
     "concrete.input_bounds: unknown input 'w' (got {'w': [0, 1]}); expected a map with one [lo, hi] pair for each of u (every input exactly once), or a list of pairs in that order"),
    (("input_bounds: [[0, 1]]", "input_bounds: {}"), "concrete.input_bounds: no pair for input 'u' (got {})"),
    (("input_bounds: [[0, 1]]", "input_bounds: {u: [0, 1], u: [0, 1]}"), "malformed YAML (duplicate key 'u' in concrete.input_bounds); expected every key once in a mapping"),
    (("input_bounds: [[0, 1]]", "input_bounds: {u: [1, 0]}"), "concrete.input_bounds[0]: lo = 1.0 > hi = 0.0"),
    (("output_set: [[-120, 0]]", "output_set: {y: [-120, 0]}"), "concrete.output_set: unknown output 'y' (got {'y': [-120, 0]}); expected a map with one [lo, hi] pair for each of y1"),
    (("output_set: [[-120, 0]]", "output_set: {y1: [-120, 0], y2: [0, 1]}"), "concrete.output_set: unknown output 'y2'"),
])
def test_bounds_map_problems_named(pair, fragment):
    assert fragment in error_of(cuk(pair))


def test_explicit_m_is_optional_and_hashed_only_when_given():
    plain = parse_spec_text(cuk())
    assert plain.abstract.m is None
    given = parse_spec_text(cuk(("  domain: [[0, 0.95]]\n", '  domain: [[0, 0.95]]\n  m: ["x4"]\n')))
    assert given.abstract.m == ["x4"] and given.sha256 != plain.sha256
    assert "abstract.m: has 2 entries; expected 1" in error_of(cuk(("  domain: [[0, 0.95]]\n", '  domain: [[0, 0.95]]\n  m: ["x4", "x3"]\n')))


# --- the guaranteed controller and timed levels (issue 15, docs/guaranteed.md) ------------------------------------

SETPOINT = "{kind: setpoint, gain: 80.0, v_max: 60.0}"
LEVELS = "reference_levels: [-19.11, -80.90, -44.27, -4.31, -12.48, -32.91]"


def test_guaranteed_controller_loads_with_mode_auto_by_default():
    spec = parse_spec_text(cuk((SETPOINT, "{kind: guaranteed, tolerance: 5, gain: 80.0}")))
    ctl = spec.simulate.tracking.abstract_controller
    assert (ctl.kind, ctl.tolerance, ctl.gain, ctl.mode) == ("guaranteed", 5.0, 80.0, "auto")
    assert not hasattr(ctl, "v_max")
    for mode in ("budget", "governor", "auto"):
        assert parse_spec_text(cuk((SETPOINT, f"{{kind: guaranteed, tolerance: 5, gain: 80.0, mode: {mode}}}"))).simulate.tracking.abstract_controller.mode == mode
    # The set-point controller is unchanged, and so is the hash of every spec that uses it.
    setpoint = parse_spec_text(cuk()).simulate.tracking.abstract_controller
    assert (setpoint.kind, setpoint.gain, setpoint.v_max) == ("setpoint", 80.0, 60.0)


def test_the_guaranteed_spec_of_the_tests_is_the_cuk_spec_but_for_its_controller():
    from .conftest import ROOT
    spec = load_spec(ROOT / "tests" / "specs" / "cuk_guaranteed.yaml")
    base = load_spec(CUK)
    assert spec.concrete == base.concrete and spec.abstract == base.abstract and spec.stabilisability == base.stabilisability
    assert spec.simulate.tracking.reference_levels == base.simulate.tracking.reference_levels
    assert spec.simulate.tracking.abstract_controller.tolerance == 5.0


@pytest.mark.parametrize("controller, line", [
    ("{kind: pid, gain: 80.0}",
     "simulate.tracking.abstract_controller.kind: kind 'pid' is not one of the kinds; expected kind: setpoint or guaranteed"),
    ("{gain: 80.0}", "simulate.tracking.abstract_controller: no kind given (got {'gain': 80.0}); expected kind: setpoint or guaranteed"),
    ("{kind: guaranteed, tolerance: 5, gain: 80.0, v_max: 3}",
     "simulate.tracking.abstract_controller.v_max: unknown key 'v_max'; expected one of the keys gain, kind, mode, tolerance"),
    ("{kind: guaranteed, tolerence: 5, gain: 80.0}",
     "simulate.tracking.abstract_controller.tolerence: unknown key 'tolerence' (did you mean 'tolerance'?); expected one of the keys gain, kind, mode, tolerance"),
    ("{kind: setpoint, gain: 80.0, v_max: 60.0, tolerance: 5}",
     "simulate.tracking.abstract_controller.tolerance: unknown key 'tolerance'; expected one of the keys gain, kind, v_max"),
    ("{kind: guaranteed, gain: 80.0}", "simulate.tracking.abstract_controller.tolerance: missing; expected this key"),
    ("{kind: guaranteed, tolerance: 0, gain: 80.0}",
     "simulate.tracking.abstract_controller.tolerance: Input should be greater than 0 (got 0); expected a number > 0"),
    ("{kind: guaranteed, tolerance: .inf, gain: 80.0}", "simulate.tracking.abstract_controller.tolerance"),
    ("{kind: guaranteed, tolerance: 5, gain: 80.0, mode: fast}",
     "simulate.tracking.abstract_controller.mode: Input should be 'auto', 'budget' or 'governor' (got 'fast'); expected 'auto', 'budget' or 'governor'"),
])
def test_controller_problems_are_one_line_naming_the_field(controller, line):
    assert line in error_of(cuk((SETPOINT, controller)))


def test_timed_levels_load_next_to_plain_ones():
    text = cuk((LEVELS, "reference_levels: [-19.11, {level: -80.9, by: 3.0, hold: 2.0}, [-44.27], -4.31]"),
               (SETPOINT, "{kind: guaranteed, tolerance: 5, gain: 80.0}"))
    tr = parse_spec_text(text).simulate.tracking
    timed = tr.reference_levels[1]
    assert (timed.level, timed.by, timed.hold) == (-80.9, 3.0, 2.0)
    assert tr.level_values() == [-19.11, -80.9, [-44.27], -4.31]
    # Level k is held from k dwell; the last one to t_final (dwell 5, t_final 30).
    assert tr.segment(0) == (0.0, 5.0) and tr.segment(1) == (5.0, 10.0) and tr.segment(3) == (15.0, 30.0)


@pytest.mark.parametrize("levels, controller, line", [
    ("[-19.11, {level: -80.9, by: 3.0, hold: 2.5}, -44.27]", "guaranteed",
     "simulate.tracking.reference_levels[1].hold: by + hold = 5.5 s runs past the 5 s this level is held"),
    ("[-19.11, -44.27, {level: -80.9, by: 20.0, hold: 5.5}]", "guaranteed",     # the last level: from 10 s to t_final = 30 s
     "simulate.tracking.reference_levels[2].hold: by + hold = 25.5 s runs past the 20 s this level is held"),
    ("[-19.11, {level: -80.9, by: 3.0, hold: 2.0}]", "setpoint",
     "simulate.tracking.reference_levels[1]: has a deadline (by, hold) but the controller is 'setpoint', which guarantees no tolerance"),
    ("[-19.11, {level: -80.9, by: 3.0, hodl: 2.0}]", "guaranteed",
     "simulate.tracking.reference_levels[1].hodl: unknown key 'hodl' (did you mean 'hold'?); expected one of the keys by, hold, level"),
    ("[-19.11, {level: -80.9, by: -3.0, hold: 2.0}]", "guaranteed",
     "simulate.tracking.reference_levels[1].by: Input should be greater than or equal to 0 (got -3.0); expected a number >= 0"),
    ("[-19.11, {level: [-80.9, 1.0], by: 3.0, hold: 2.0}]", "guaranteed",
     "simulate.tracking.reference_levels[1].level: has 2 values; expected 1 (one per output)"),
    ("[-19.11, {by: 3.0, hold: 2.0}]", "guaranteed", "simulate.tracking.reference_levels[1].level: missing"),
])
def test_timed_level_problems_are_named(levels, controller, line):
    ctl = SETPOINT if controller == "setpoint" else "{kind: guaranteed, tolerance: 5, gain: 80.0}"
    assert line in error_of(cuk((LEVELS, f"reference_levels: {levels}"), (SETPOINT, ctl)))


def test_a_timed_level_the_run_never_reaches_is_refused():
    text = cuk((LEVELS, "reference_levels: [-19.11, -80.9, -44.27, -4.31, -12.48, -32.91, {level: -30, by: 1, hold: 1}]"),
               (SETPOINT, "{kind: guaranteed, tolerance: 5, gain: 80.0}"))
    assert "simulate.tracking.reference_levels[6]: has a deadline but the run ends (t_final = 30 s) before level 6 is asked for" in error_of(text)
