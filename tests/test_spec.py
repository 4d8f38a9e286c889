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
