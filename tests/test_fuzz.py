"""Fuzzing: random specs and expression strings either load or raise ashc's own error, never anything else.

The regular suite runs a few thousand cases; `make fuzz` runs many more (ASHC_FUZZ_EXAMPLES).
"""

import os
import time

import pytest
import sympy as sp
import yaml
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from ashc_cli.errors import AshcError
from ashc_cli.problem.expr import parse_expression
from ashc_cli.problem.model import build_model
from ashc_cli.problem.spec import parse_spec_text

from .conftest import CUK

EXAMPLES = int(os.environ.get("ASHC_FUZZ_EXAMPLES", "1500"))
FUZZ = settings(max_examples=EXAMPLES, deadline=None, suppress_health_check=list(HealthCheck), derandomize="ASHC_FUZZ_EXAMPLES" not in os.environ)
NAMES = {n: sp.Symbol(n, real=True) for n in ("x1", "x2", "xi", "E")}
BASE = yaml.safe_load(CUK.read_text())

tokens = st.sampled_from(["x1", "x2", "xi", "E", "q", "pi", "t", "0", "1", "2.5", "1e308", "-", "+", "*", "/", "**", "^", "(", ")", ",", ".",
                          "sqrt", "sin", "exp", "log", "abs", "min", "max", "triangle", "__import__", "'os'", "[", "]", "lambda", ":",
                          "if", "else", "{", "}", "f'", "\"", "9", "**9", " ", "=", "@", "%", "//", "~", "not", "and", "1j"])
expression_text = st.one_of(st.text(max_size=80), st.lists(tokens, max_size=30).map("".join))


def loads_or_ashc_error(fn):
    try:
        fn()
    except AshcError as exc:
        assert exc.exit_code in (2, 3, 4, 5) and "\n" not in exc.line()


@FUZZ
@given(expression_text, st.booleans())
def test_random_expressions(text, signal):
    start = time.process_time()           # CPU time of this process: the parser's work, whatever the machine's load
    loads_or_ashc_error(lambda: parse_expression(text, NAMES, "field", signal=signal))
    assert time.process_time() - start < 1.0


json_values = st.recursive(st.none() | st.booleans() | st.integers() | st.floats() | st.text(max_size=20),
                           lambda inner: st.lists(inner, max_size=4) | st.dictionaries(st.text(max_size=8), inner, max_size=4), max_leaves=10)


def paths(node, prefix=()):
    yield prefix
    if isinstance(node, dict):
        for k, v in node.items():
            yield from paths(v, prefix + (k,))
    elif isinstance(node, list):
        for i, v in enumerate(node):
            yield from paths(v, prefix + (i,))


ALL_PATHS = [p for p in paths(BASE) if p]


def mutate(base, path, value, delete):
    import copy

    spec = copy.deepcopy(base)
    node = spec
    for key in path[:-1]:
        node = node[key]
    if delete and isinstance(node, dict):
        node.pop(path[-1], None)
    else:
        node[path[-1]] = value
    return spec


@pytest.mark.slow
@FUZZ
@given(st.sampled_from(ALL_PATHS), json_values | expression_text, st.booleans())
def test_random_specs(path, value, delete):
    spec_text = yaml.safe_dump(mutate(BASE, path, value, delete), allow_unicode=True)
    loads_or_ashc_error(lambda: build_model(parse_spec_text(spec_text)))


@settings(max_examples=max(200, EXAMPLES // 5), deadline=None, suppress_health_check=list(HealthCheck), derandomize="ASHC_FUZZ_EXAMPLES" not in os.environ)
@given(st.text(max_size=300))
def test_random_yaml_text(text):
    loads_or_ashc_error(lambda: parse_spec_text(text))
