"""The catalogue of bad inputs ashc is tried on, with the exit code and message each must get.

Used by ``tests/test_bad_inputs.py`` (every case is run in the suite) and by
``python -m tests.bad_inputs docs/bad-inputs.md`` (``make docs``), which writes the table of inputs and the
messages they actually get.  Each case edits the paper's Cuk spec (``specs/cuk_converter.yaml``), or
replaces it with raw text, and runs the stages it needs in-process.
"""

from __future__ import annotations

import sys
import tempfile
from dataclasses import dataclass
from pathlib import Path

from ashc_cli.errors import AshcError
from ashc_cli.design.pipeline import DESIGN, run
from ashc_cli.problem.spec import parse_spec_text

ROOT = Path(__file__).resolve().parents[1]
CUK = ROOT / "specs" / "cuk_converter.yaml"
CUK_PAPER_M = ROOT / "specs" / "cuk_converter_paper_M.yaml"
LEFT_INVERSE = ROOT / "specs" / "linear_left_inverse.yaml"



@dataclass(frozen=True)
class Case:
    """One bad input: how to make it, what must come back."""

    id: str
    what: str
    edits: tuple[tuple[str, str], ...] = ()
    raw: str | None = None
    base: Path = CUK
    targets: tuple[str, ...] = DESIGN
    code: int = 2
    fragment: str = ""
    drop_tracking: bool = False
    #: Run ``ashc synthesize`` on the design (a task that cannot be met).
    synthesize: bool = False

    def text(self) -> str:
        if self.raw is not None:
            return self.raw
        text = self.base.read_text()
        for old, new in self.edits:
            if old not in text:
                raise AssertionError(f"case {self.id}: {old!r} not in {self.base.name}")
            text = text.replace(old, new)
        if self.drop_tracking:
            start = text.index("  tracking:")
            end = text.index("  m_relation:")
            text = text[:start] + text[end:]
        return text


CASES: tuple[Case, ...] = (
    # --- YAML and structure -------------------------------------------------------------------------
    Case("yaml-malformed", "malformed YAML", raw="name: [\n", fragment="malformed YAML"),
    Case("yaml-not-mapping", "top level is a list", raw="- 1\n- 2\n", fragment="top level is a list"),
    Case("yaml-duplicate-key", "a key given twice", raw="name: a\nname: b\n", fragment="duplicate key 'name'"),
    Case("yaml-alias", "YAML aliases (billion-laughs vector)", raw="a: &x [1, 2]\nb: *x\n", fragment="aliases"),
    Case("yaml-python-tag", "a python object tag", raw="name: !!python/object/apply:os.system ['echo hi']\n", fragment="malformed YAML"),
    Case("key-unknown", "a misspelt key", edits=(('  delta: "', '  detla: "'),), fragment="unknown key 'detla' (did you mean 'delta'?); expected one of the keys"),
    Case("key-missing", "a required key left out", edits=(('  h: ["x4"]\n', ""),), fragment="concrete.h: missing"),
    Case("len-f_bar", "f_bar not n long", edits=(('"x1/C_2", ', ""),), fragment="concrete.f_bar: has 3 entries; expected 4"),
    Case("len-g", "g not n x m", edits=(('["0"]]', '["0", "1"]]'),), fragment="concrete.g[3]: has 2 entries; expected 1"),
    Case("f-and-g", "concrete.f given with f_bar and g", edits=(('  h: ["x4"]', '  f: ["x1", "x2", "x3", "x4"]\n  h: ["x4"]'),),
         fragment="concrete.f: given with f_bar and g; expected either f"),
    Case("disturbance-no-e", "disturbances without e", edits=(('  h: ["x4"]', '  h: ["x4"]\n  disturbances: [w]\n  disturbance_bounds: [[-1, 1]]'),),
         fragment="concrete.e: is missing (concrete.disturbances is given)"),
    Case("disturbance-e-shape", "e not n x d", edits=(('  h: ["x4"]', '  h: ["x4"]\n  disturbances: [w]\n  e: [["1"], ["0"]]\n  disturbance_bounds: [[-1, 1]]'),),
         fragment="concrete.e: has 2 entries; expected 4"),
    Case("f-least-squares", "f not affine in u with q least_squares", edits=(
        ('  f_bar: ["(-R_i*x1 - x2 + E)/L_1", "x1/C_2", "-x4/L_3", "(x3 - G_L*x4)/C_4"]\n  g: [["x2/L_1"], ["(x3 - x1)/C_2"], ["-x2/L_3"], ["0"]]',
         '  f: ["(-R_i*x1 - x2 + E + x2*u**2)/L_1", "x1/C_2", "-x4/L_3", "(x3 - G_L*x4)/C_4"]'),),
         fragment="interface.q: least_squares needs g(x) of an input-affine plant"),
    Case("len-h", "h longer than output_set", edits=(('h: ["x4"]', 'h: ["x4", "x2"]'),), fragment="concrete.output_set: has 1 entries; expected 2"),
    Case("pair-not-pair", "a bound that is not a pair", edits=(("input_bounds: [[0, 1]]", "input_bounds: [[0]]"),), fragment="concrete.input_bounds[0]"),
    Case("pair-lo-gt-hi", "a bound with lo > hi", edits=(("input_bounds: [[0, 1]]", "input_bounds: [[1, 0]]"),), fragment="lo = 1.0 > hi = 0.0"),
    Case("digits-beyond-double", "a bound with more digits than a double holds", edits=(("input_bounds: [[0, 1]]", "input_bounds: [[0, 0.99999999999999999]]"),),
         fragment="concrete.input_bounds[0][1]: 0.99999999999999999 has more significant digits than a double holds (it would be read as 1.0)"),
    Case("param-nan", "a NaN parameter", edits=(("E: 12.0", "E: .nan"),), fragment="parameters.E"),
    Case("param-inf", "an infinite parameter", edits=(("E: 12.0", "E: .inf"),), fragment="parameters.E"),
    Case("param-not-number", "a parameter that is not a number", edits=(("E: 12.0", "E: twelve"),), fragment="parameters.E"),
    Case("enum-method", "an unknown stabilisability method", edits=(("method: polytopic_lmi", "method: lmi"),), fragment="stabilisability.method"),
    Case("rate-negative", "a negative decay rate", edits=(("decay_rate: 2.0", "decay_rate: -2"),), fragment="stabilisability.decay_rate"),
    Case("enum-structure", "an unknown form of M", edits=(("decay_rate: 2.0", "decay_rate: 2.0\n  structure: banded"),), fragment="stabilisability.structure: Input should be 'auto', 'full' or 'diagonal' (got 'banded')"),
    Case("given-no-M", "method given without M", edits=(("method: polytopic_lmi", "method: given"),), fragment="stabilisability.M: missing"),
    Case("given-M-asymmetric", "a given M that is not symmetric", base=CUK_PAPER_M, edits=(("[ 0.4804, 0.0102,", "[ 0.4804, 0.0202,"),), fragment="stabilisability.M: is not symmetric"),
    Case("given-M-indefinite", "a given M that is not positive definite", base=CUK_PAPER_M, edits=(("[ 0.4804, 0.0102,", "[-0.4804, 0.0102,"),), code=3, fragment="is not positive definite"),
    Case("bounds-map-unknown", "input_bounds as a map with a name that is not an input", edits=(("input_bounds: [[0, 1]]", "input_bounds: {w: [0, 1]}"),),
         fragment="concrete.input_bounds: unknown input 'w' (got {'w': [0, 1]}); expected a map with one [lo, hi] pair for each of u"),
    Case("bounds-map-missing", "input_bounds as a map missing an input", base=LEFT_INVERSE, edits=(("input_bounds: {u1: [-3, 3], u2: [-3, 3]}", "input_bounds: {u1: [-3, 3]}"),),
         fragment="concrete.input_bounds: no pair for input 'u2'"),
    Case("bounds-map-duplicate", "input_bounds as a map naming an input twice", edits=(("input_bounds: [[0, 1]]", "input_bounds: {u: [0, 1], u: [0, 0.5]}"),),
         fragment="duplicate key 'u' in concrete.input_bounds"),
    Case("output-set-map-unknown", "output_set as a map not keyed by y1..yp", edits=(("output_set: [[-120, 0]]", "output_set: {x4: [-120, 0]}"),),
         fragment="concrete.output_set: unknown output 'x4'"),
    Case("m-length", "an explicit m of the wrong length", edits=(("  domain: [[0, 0.95]]\n", '  domain: [[0, 0.95]]\n  m: ["x4", "x3"]\n'),),
         fragment="abstract.m: has 2 entries; expected 1"),
    Case("m-abstract-name", "an explicit m using an abstract state", edits=(("  domain: [[0, 0.95]]\n", '  domain: [[0, 0.95]]\n  m: ["xi*x4"]\n'),),
         fragment="abstract.m[0]: uses xi; expected an expression in the concrete states and parameters only"),
    Case("sim-xi0-length", "xi0 of the wrong length", edits=(("xi0: [0.6156]", "xi0: [0.6, 0.1]"),), fragment="simulate.tracking.xi0: has 2 entries"),
    # --- names ----------------------------------------------------------------------------------------
    Case("name-clash-param", "a state named like a parameter", edits=(("states: [x1, x2, x3, x4]", "states: [x1, x2, x3, E]"),), fragment="name 'E' is already used in parameters"),
    Case("name-function", "a state named like a function", edits=(("states: [xi]", "states: [exp]"),), fragment="reserved"),
    Case("name-keyword", "a state named like a Python keyword", edits=(("states: [xi]", "states: [lambda]"),), fragment="reserved"),
    Case("name-time", "a state named t", edits=(("states: [xi]", "states: [t]"),), fragment="reserved"),
    # --- expressions ----------------------------------------------------------------------------------
    Case("expr-undeclared", "an undeclared name", edits=(('"x1/C_2"', '"x5/C_2"'),), fragment="concrete.f_bar[1]: unknown name 'x5'"),
    Case("expr-typo-name", "a misspelt parameter name", edits=(('"x1/C_2"', '"x1/C2"'),),
         fragment="concrete.f_bar[1]: unknown name 'C2' (did you mean 'C_2'?); expected one of the declared names"),
    Case("expr-typo-function", "a misspelt function", edits=(('"x1/C_2"', '"sine(x1)/C_2"'),),
         fragment="concrete.f_bar[1]: call of 'sine' is not allowed (did you mean 'sin'?); expected one of the functions"),
    Case("expr-wrong-side", "an abstract state in the concrete drift", edits=(('"x1/C_2"', '"xi/C_2"'),), fragment="concrete.f_bar[1]: uses xi"),
    Case("expr-syntax", "a syntax error", edits=(('"x1/C_2"', '"x1/"'),), fragment="concrete.f_bar[1]: syntax error"),
    Case("expr-div-zero", "a division by a literal zero", edits=(('"x1/C_2"', '"x1/0"'),), fragment="division by zero"),
    Case("expr-div-zero-expr", "a division by a constant expression equal to zero", edits=(('"x1/C_2"', '"x1/(2 - 2)"'),), fragment="division by zero"),
    Case("expr-import", "code injection through __import__", edits=(('"x1/C_2"', "\"__import__('os').system('touch /tmp/pwned')\""),), fragment="is not allowed"),
    Case("expr-attribute", "attribute access", edits=(('"x1/C_2"', '"x1.real"'),), fragment="'x1.real' is not allowed"),
    Case("expr-lambda", "a lambda", edits=(('"x1/C_2"', '"(lambda: 1)()"'),), fragment="is not allowed"),
    Case("expr-index", "indexing", edits=(('"x1/C_2"', '"[x1][0]"'),), fragment="is not allowed"),
    Case("expr-fstring", "an f-string", edits=(('"x1/C_2"', "\"f'{x1}'\""),), fragment="is not allowed"),
    Case("expr-huge-power", "a huge literal power", edits=(('"x1/C_2"', '"9**9**9**9"'),), fragment="too large"),
    Case("expr-long", "a very long expression", edits=(('"x1/C_2"', '"' + "x1+" * 1000 + 'x1"'),), fragment="characters long"),
    Case("expr-deep", "a deeply nested expression", edits=(('"x1/C_2"', '"' + "sin(" * 100 + "x1" + ")" * 100 + '"'),), fragment="nested deeper"),
    Case("expr-not-string", "an expression that is a mapping", edits=(('"x1/C_2"', "{a: 1}"),), fragment="concrete.f_bar[1]"),
    Case("expr-signal-outside", "a time signal in the plant", edits=(('"x1/C_2"', '"triangle(x1)"'),), fragment="call of 'triangle' is not allowed"),
    # --- design conditions --------------------------------------------------------------------------------
    Case("plant-not-affine", "f not affine in x for polytopic_lmi", edits=(('"x1/C_2"', '"x1**2/C_2"'),), code=3, fragment="not affine in x"),
    Case("lmi-infeasible", "an infeasible decay rate", edits=(("decay_rate: 2.0", "decay_rate: 3.0"),), code=3, fragment="(the largest the solver certifies)"),
    Case("l-outside-U", "l(V) outside U", edits=(('l: ["xi"]', 'l: ["2*xi"]'),), code=3, fragment="is not inside U"),
    Case("pde-not-fitted", "an invariance PDE that 64 pieces of degree 1 do not fit (Cuk with phi_bar = -xi, pde_max_degree: 1)",
         edits=(('phi_bar: ["0"]', 'phi_bar: ["-xi"]\n  pde_max_degree: 1'),), code=3,
         fragment="no piecewise polynomial (64 pieces of degree 1) solves eq. (14a) to 1e-08: near xi in ["),
    Case("sylvester-resonant", "a linear plant whose eigenvalues S shares", base=ROOT / "specs" / "linear_double.yaml",
         edits=(('phi_bar: ["xi2", "-2*xi1 - xi2"]', 'phi_bar: ["xi2", "-xi1 - xi2"]'), ("c: 0.5", "c: 0.0")), code=3, fragment="share an eigenvalue"),
    Case("p-not-injective", "kappa not injective on V", edits=(("domain: [[0, 0.95]]", "domain: [[0, 1.0]]"),), code=3, fragment="p is not injective on V"),
    Case("V-not-covering-Y", "V not covering Y", edits=(("domain: [[0, 0.95]]", "domain: [[0, 0.9]]"),), code=3, fragment="does not cover Y"),
    Case("Y-beyond-m-real", "Y beyond where m is real", edits=(("output_set: [[-120, 0]]", "output_set: [[-130, 0]]"),), code=3, fragment="where m is real"),
    Case("delta-rank", "delta losing rank on V", edits=(('delta: "((xi - 1)**2 + G_L*R_i*xi**2)**2"', 'delta: "xi - 0.5"'),), code=3, fragment="delta loses row rank on V"),
    Case("m-not-left-inverse", "an explicit m that is not a left inverse of p on V", edits=(("  domain: [[0, 0.95]]\n", '  domain: [[0, 0.95]]\n  m: ["-x4/E"]\n'),),
         code=3, fragment="abstract.m: the given m is not a left inverse of p on V"),
    Case("m-fails-condition-ii", "an explicit m = P^+ (x - p0), a left inverse failing condition (ii)", base=LEFT_INVERSE,
         edits=(("  delta: identity\n", '  delta: identity\n  m: ["(5*x1 - x2 + 2*x3 - 5*x4 - 2.4)/11", "(-x1 + 9*x2 + 4*x3 + x4 - 0.4)/11"]\n'),),
         code=3, fragment="abstract.m: the given m fails condition (ii) of Theorem 6"),
    Case("no-left-inverse-ii", "an affine p where no left inverse K of P has C (I - P K) = 0 (three outputs, two abstract states)", base=LEFT_INVERSE,
         edits=(('h: ["x3"]', 'h: ["x3", "x1", "x2"]'), ("output_set: {y1: [-0.5, 0.5]}", "output_set: {y1: [0.2, 0.2], y2: [0.4, 0.4], y3: [0, 0]}")),
         drop_tracking=True, code=3, fragment="no left inverse K of P satisfies C (I - P K) = 0"),
    # --- simulation ------------------------------------------------------------------------------------------
    Case("sim-xi0-outside-V", "xi0 outside V", edits=(("xi0: [0.6156]", "xi0: [0.99]"),), targets=("simulate",), code=3, fragment="is outside V"),
    Case("sim-level-unreachable", "a reference level kappa never reaches on V", edits=(("reference_levels: [-19.11,", "reference_levels: [-130,"),), targets=("simulate",), code=3, fragment="is not reached by kappa"),
    Case("sim-leaves-m-real", "the m-relation run leaves where m is certified", edits=(("x0: [10.3256, 2.0561, -4.9785, -6.9732]", "x0: [0, 0, 0, 0]"), ('u: "0.3*triangle(t - 2) + 0.1*sin(2*pi*(t - 2)) + 0.45"', 'u: "0.95"')),
         targets=("simulate",), drop_tracking=True, code=3, fragment="leaves kappa(V) = [-126.188, 0], where m is certified"),
    Case("sim-u-bad-name", "an unknown name in the m-relation input signal", edits=(('u: "0.3*triangle(t - 2)', 'u: "0.3*triangle(s - 2)'),), targets=("simulate",), drop_tracking=True, code=2, fragment="unknown name 's'"),
    Case("param-zero-divides", "a parameter of 0 that an expression divides by", edits=(("L_1: 10.0e-3", "L_1: 0"),),
         fragment="concrete.f_bar[0]: is not finite with the parameter values (L_1 = 0: a division by zero)"),
    Case("task-past-horizon", "a task deadline whose hold runs past the horizon", edits=(('units: {t: s, y: V}', 'units: {t: s, y: V}' + "\ntask: {horizon: 10, reach: [{set: [[-82, -78]], by: 8, hold: 5}]}"),), fragment='task.reach[0].by: by + hold = 13 s is past the horizon 10 s'),
    Case("task-set-size", "a task set with two intervals for one output", edits=(('units: {t: s, y: V}', 'units: {t: s, y: V}' + "\ntask: {horizon: 10, always: [[-110, -1], [0, 1]]}"),), fragment='task.always: has 2 entries; expected 1'),
    Case("task-empty-set", "a task set with lo >= hi", edits=(('units: {t: s, y: V}', 'units: {t: s, y: V}' + "\ntask: {horizon: 10, avoid: [{set: [[-60, -70]], during: [0, 2]}]}"),), fragment='task.avoid[0].set[0]: lo = -60 >= hi = -70'),
    Case("task-window", "an avoid window past the horizon", edits=(('units: {t: s, y: V}', 'units: {t: s, y: V}' + "\ntask: {horizon: 10, avoid: [{set: [[-70, -60]], during: [5, 12]}]}"),), fragment='task.avoid[0].during: [5, 12]'),
    Case("task-order", "reaches out of the order of their deadlines", edits=(('units: {t: s, y: V}', 'units: {t: s, y: V}' + "\ntask: {horizon: 30, reach: [{set: [[-82, -78]], by: 20}, {set: [[-22, -18]], by: 10}]}"),), fragment='task.reach[1].by: 10 s is before the deadline of reach 0'),
    Case("task-nothing", "a task that asks for nothing", edits=(('units: {t: s, y: V}', 'units: {t: s, y: V}' + "\ntask: {horizon: 10}"),), fragment='task: asks for nothing'),
)


#: Plants of our own for the messages that must name the real cause (issue 39): a ring of 13 states each with a sin
#: term (more terms than the vertices enumerate), an unstable plant written as f(x, u) (not input-affine: no
#: linear_gain), and a levitated gap whose equilibrium gap^2 = xi has a root outside the state box.
MANY_TERMS = """name: many_terms
concrete:
  states: ["x0", "x1", "x2", "x3", "x4", "x5", "x6", "x7", "x8", "x9", "x10", "x11", "x12"]
  inputs: [u]
  f_bar: ["-x0 + 0.9*sin(x1)", "-x1 + 0.9*sin(x2)", "-x2 + 0.9*sin(x3)", "-x3 + 0.9*sin(x4)", "-x4 + 0.9*sin(x5)", "-x5 + 0.9*sin(x6)", "-x6 + 0.9*sin(x7)", "-x7 + 0.9*sin(x8)", "-x8 + 0.9*sin(x9)", "-x9 + 0.9*sin(x10)", "-x10 + 0.9*sin(x11)", "-x11 + 0.9*sin(x12)", "-x12 + 0.9*sin(x0)"]
  g: [["1"], ["0"], ["0"], ["0"], ["0"], ["0"], ["0"], ["0"], ["0"], ["0"], ["0"], ["0"], ["0"]]
  h: ["x0"]
  input_bounds: [[-1, 1]]
  output_set: [[-0.5, 0.5]]
  state_box: [[-2, 2], [-2, 2], [-2, 2], [-2, 2], [-2, 2], [-2, 2], [-2, 2], [-2, 2], [-2, 2], [-2, 2], [-2, 2], [-2, 2], [-2, 2]]
stabilisability: {method: polytopic_lmi, decay_rate: 0.5}
abstract: {states: [xi], inputs: [v], phi_bar: ["0"], l: ["xi"], domain: [[-0.5, 0.5]]}
"""
UNSTABLE_GENERAL = """name: unstable_general
concrete: {states: [x], inputs: [u], f: ["x + sin(u)"], h: ["x"], input_bounds: [[-1, 1]], output_set: [[-0.5, 0.5]], state_box: [[-2, 2]]}
stabilisability: {method: polytopic_lmi, decay_rate: 0.5}
abstract: {states: [xi], inputs: [v], phi_bar: ["0"], l: ["xi"], domain: [[-0.4, 0.4]]}
"""
LEVITATED = """name: levitated
concrete:
  states: [gap, speed]
  inputs: [u]
  f_bar: ["speed", "-gap**2 - speed"]
  g: [["0"], ["1"]]
  h: ["gap"]
  input_bounds: [[0, 5]]
  output_set: [[1.1, 1.9]]
  state_box: [[-0.5, 0.5], [-2, 2]]
stabilisability: {method: polytopic_lmi, decay_rate: 0.5}
abstract: {states: [xi], inputs: [v], phi_bar: ["0"], l: ["xi"], domain: [[1, 4]]}
"""

CART = """name: cart
concrete:
  states: [px, py, th, s]
  inputs: [a, w]
  f_bar: ["s*cos(th)", "s*sin(th)", "0", "0"]
  g: [["0", "0"], ["0", "0"], ["0", "1"], ["1", "0"]]
  h: ["px", "py"]
  input_bounds: [[-1, 1], [-1, 1]]
  output_set: [[-1, 1], [-1, 1]]
  state_box: [[-2, 2], [-2, 2], [-3.1, 3.1], [0, 2]]
stabilisability: {method: polytopic_lmi, decay_rate: 0.5}
abstract: {states: [xi1, xi2], inputs: [v1, v2], phi_bar: ["0", "0"], l: ["0", "0"], domain: [[-1, 1], [-1, 1]]}
"""

LAG_TASK = """name: lag_task
concrete: {states: [x], inputs: [u], f_bar: ["-2*x"], g: [["1"]], h: ["x"], input_bounds: [[-4, 4]], output_set: [[-1, 1]]}
stabilisability: {method: polytopic_lmi, decay_rate: 2.0}
abstract: {states: [xi], inputs: [v], phi_bar: ["0"], l: ["2*xi"], domain: [[-1.5, 1.5]]}
task:
  horizon: 12.0
  always: [[-2, 2]]
  reach:
    - {set: [[0.5, 0.9]], by: 8.0, hold: 2.0}
  xi0: [0.0]
"""

CASES += (
    Case("task-avoid-across", "an avoid set across the route to reach[0] for its whole window", code=3, synthesize=True,
         raw=LAG_TASK.replace("  xi0: [0.0]", "  avoid:\n    - {set: [[0.2, 0.3]], during: [0.0, 12.0]}\n  xi0: [0.0]"),
         fragment="task.avoid[0]: lies across every route of psi = kappa(xi) from the start (psi = 0) to task.reach[0]"),
    Case("task-reach-unreachable", "a reach set no output of the abstraction meets", code=3, synthesize=True,
         raw=LAG_TASK.replace("[[0.5, 0.9]]", "[[1.6, 1.9]]"),
         fragment="task.reach[0].set: lies outside every output the abstraction can produce: psi = kappa(xi) for xi in V spans [-1.5, 1.5]"),
    Case("not-contracting", "a cart whose position does not contract (identity feedback)", raw=CART, targets=("stabilise",), code=3,
         fragment="stabilisability: no M certifies any decay rate lambda > 0 (eq. (28)): at x = [0, 0, 0, 1] df/dx has the eigenvalue 0"),
    Case("not-stabilisable", "the cart with linear_gain: speed 0 in the box", raw=CART.replace("decay_rate: 0.5}", "decay_rate: 0.5, feedback: linear_gain}"),
         targets=("stabilise",), code=3, fragment="at x = [0, 0, 0, 0] the mode s = 0 of df/dx (Re s >= -lambda/2 = -0.25) is not reachable from the inputs"),

    Case("terms-too-many", "13 distinct nonlinear terms in df/dx, the norm-bound test proves 0.2 < 0.5", raw=MANY_TERMS, targets=("stabilise",), code=3,
         fragment="at most, below the decay_rate 0.5; expected decay_rate <= 0.2"),
    Case("unstable-not-affine", "an unstable plant written as f(x, u)", raw=UNSTABLE_GENERAL, targets=("stabilise",), code=3,
         fragment="expected a plant that is incrementally stable on the set"),
    Case("p-outside-box", "every solution of eq. (14a) outside the state box", raw=LEVITATED, targets=("manifold",), code=3,
         fragment="abstract.p: eq. (14a) has 2 solution(s) real on V, and none lies in concrete.state_box"),
)


def diagnose(case: Case, out: Path) -> tuple[int, str]:
    """Run a case; return (exit code, the one-line message), or (0, '') if it unexpectedly succeeds."""
    try:
        spec = parse_spec_text(case.text(), "spec")
        arts = run(spec, out, case.targets)
        if case.synthesize:
            from ashc_cli.design.pipeline import design_model
            from ashc_cli.products.synthesize import synthesize

            synthesize(design_model(spec, arts), arts)
    except AshcError as exc:
        return exc.exit_code, exc.line()
    return 0, ""


def table(results: list[tuple[Case, int, str]]) -> str:
    """The markdown page of every case and the message it gets."""
    lines = [
        "# Bad inputs and what ashc answers",
        "",
        "Generated by `make docs` (`python -m tests.bad_inputs docs/bad-inputs.md`); every row is also a test",
        "(`tests/test_bad_inputs.py`). Each input is the paper's Cuk spec with one edit, or (the last rows) a small plant",
        "of our own written in `tests/bad_inputs.py`. The message is what the",
        "CLI prints after `error: `, and the code is the exit status (2 spec, 3 design condition, 4 numerical,",
        "5 artefact).",
        "",
        "| case | bad input | code | message |",
        "| --- | --- | --- | --- |",
    ]
    for case, code, message in results:
        shown = message.replace("|", "\\|")
        if len(shown) > 300:
            shown = shown[:297] + "..."
        lines.append(f"| `{case.id}` | {case.what} | {code} | {shown} |")
    return "\n".join(lines) + "\n"


def main(argv: list[str]) -> int:
    target = Path(argv[0]) if argv else ROOT / "docs" / "bad-inputs.md"
    results = []
    with tempfile.TemporaryDirectory() as tmp:
        for k, case in enumerate(CASES):
            code, message = diagnose(case, Path(tmp) / str(k))
            results.append((case, code, message))
            print(f"{case.id:<24} {code}  {message[:100]}", file=sys.stderr)
    target.parent.mkdir(parents=True, exist_ok=True)
    target.write_text(table(results))
    return 0


if __name__ == "__main__":
    raise SystemExit(main(sys.argv[1:]))
