"""Tests of the spec contract (ashc_cli.spec)."""

import pytest

from ashc_cli.errors import SpecError
from ashc_cli.spec import load_spec, parse_spec_text

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
    assert "top level is list" in error_of("- 1\n")


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
