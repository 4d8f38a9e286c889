"""``ashc regress``: rerun every spec of a folder and compare its summary with stored golden values.

A golden file ``<golden>/<spec name>.json`` holds, per key of the ``ashc summary`` object (dotted path, e.g.
``bound.gain``), the value and how it may differ:

    {"spec": "cuk_converter", "keys": {"bound.gain": {"value": 23.836, "rtol": 1e-6, "atol": 0.0}, ...}}

``rtol``/``atol`` compare |new - value| <= atol + rtol |value| (elementwise for lists); ``"at_most": true`` makes
the golden value an upper limit instead (residuals, which move with round-off but must stay small); a
boolean or string must match exactly.  ``--update`` writes the golden files from the current run with the
tolerances of :data:`TOLERANCES` (an edited tolerance survives an update).
"""

from __future__ import annotations

import json
import math
from pathlib import Path

from ashc_cli.errors import ArtefactError, SpecError
from ashc_cli.design.pipeline import DESIGN, run_for_verdict
from ashc_cli.outputs.query import summary
from ashc_cli.problem.spec import Spec, load_spec
from ashc_cli.design.verdict import verdict

__all__ = ["TOLERANCES", "compare", "collect", "regress"]

#: The keys compared, with their default tolerances (kept when a golden file is first written).
TOLERANCES: dict[str, dict] = {
    "verdict.solved": {},
    "verdict.kind": {},          # proved, sampled or fails: a design that was proved stays proved
    "stabilise.lambda": {"rtol": 1e-4, "atol": 1e-9},
    "stabilise.M_min_eigenvalue": {"rtol": 1e-3, "atol": 1e-9},
    "manifold.residual": {"at_most": True},
    "kappa.kappa_range": {"rtol": 1e-6, "atol": 1e-9},
    "inverse.V": {"rtol": 1e-9, "atol": 1e-12},
    "inverse.left_inverse_residual": {"at_most": True},
    "delta.min_singular_value": {"rtol": 1e-4, "atol": 1e-12},
    "bound.alpha_h": {"rtol": 1e-4, "atol": 1e-12},
    "bound.dbar_q0": {"rtol": 1e-4, "atol": 1e-12},
    "bound.dbar_q0_identity": {"rtol": 1e-4, "atol": 1e-12},
    "bound.gain": {"rtol": 1e-4, "atol": 1e-12},
    "bound.w0_max_certified": {"rtol": 1e-4, "atol": 1e-12},
    "bound.v_max_certified": {"rtol": 1e-4, "atol": 1e-12},
}
#: Residual limits are written this many times above the measured value (round-off moves them).
AT_MOST_FACTOR = 100.0
AT_MOST_FLOOR = 1e-12


def _get(obj: dict, dotted: str):
    for part in dotted.split("."):
        if not isinstance(obj, dict) or part not in obj:
            return None
        obj = obj[part]
    return obj


def _flat(x) -> list:
    if isinstance(x, list):
        return [y for item in x for y in _flat(item)]
    return [x]


def compare(key: str, new, golden: dict) -> str | None:
    """Why ``new`` does not match the golden entry, or None if it does.

    Parameters
    ----------
    key : str
        The dotted key (``bound.gain``), for the message.
    new : float, bool, str, list or None
        Its value in the current summary (None: missing).
    golden : dict
        The golden entry: ``value``, and ``rtol``, ``atol`` (default 0) or ``at_most``.

    Returns
    -------
    str or None
        One line naming the key, the two values and the tolerance.
    """
    old = golden["value"]
    if new is None:
        return f"{key} is missing from the summary (golden {old})"
    if isinstance(old, (bool, str)) or old is None:
        return None if new == old else f"{key} = {new!r}, golden {old!r}"
    if golden.get("at_most"):
        worst = max(abs(float(v)) for v in _flat(new))
        return None if worst <= float(old) else f"{key} = {worst:.6g} exceeds the golden limit {float(old):.6g}"
    a, b = _flat(new), _flat(old)
    if len(a) != len(b):
        return f"{key} has {len(a)} values, golden {len(b)}"
    rtol, atol = float(golden.get("rtol", 0.0)), float(golden.get("atol", 0.0))
    for x, y in zip(a, b):
        x, y = float(x), float(y)
        if not (math.isfinite(x) and math.isfinite(y)) and x != y:
            return f"{key} = {x}, golden {y}"
        if abs(x - y) > atol + rtol * abs(y):
            return f"{key} = {x:.10g} differs from golden {y:.10g} by {abs(x - y):.3g} (allowed {atol + rtol * abs(y):.3g}: rtol {rtol:g}, atol {atol:g})"
    return None


def collect(spec: Spec, out: Path) -> dict:
    """Design one spec (stage by stage, so a failing design still has a verdict) and return its summary.

    Parameters
    ----------
    spec : Spec
        The spec.
    out : Path
        The artefacts go to ``out / spec.name``.

    Returns
    -------
    dict
        The ``ashc summary`` object of the design stages that ran, with ``verdict``: ``solved`` and ``kind``.
    """
    arts, stopped = run_for_verdict(spec, out / spec.name)
    found = verdict(arts, stopped)
    result = summary({k: arts[k] for k in DESIGN if k in arts})
    result["verdict"] = {"solved": found.solved, "kind": found.kind}
    return result


def regress(specs: Path, golden: Path, out: Path, update: bool = False, progress=None) -> list[dict]:
    """Rerun every ``*.yaml`` in ``specs`` and compare with ``golden``; returns one row per spec.

    Each row: spec, status ("ok", "differs", "no golden", "updated"), and the list of differences.

    Parameters
    ----------
    specs : Path
        The folder of specs.
    golden : Path
        The folder of golden files ``<spec name>.json``.
    out : Path
        Each design's artefacts go to ``out / <spec name>``.
    update : bool
        Write the golden files from this run instead of comparing (``--update``).
    progress : callable, optional
        Called with each row as it is done.

    Returns
    -------
    list of dict
        One row per spec, in file-name order: ``spec``, ``status``, ``differences`` (list of str).

    Raises
    ------
    SpecError
        If ``specs`` holds no spec.
    ArtefactError
        If a golden file is unreadable.
    """
    paths = sorted(Path(specs).glob("*.yaml"))
    if not paths:
        raise SpecError(str(specs), "holds no *.yaml spec", "a folder of specs (e.g. specs/)")
    rows = []
    for path in paths:
        spec = load_spec(path)
        result = collect(spec, Path(out))
        name = spec.name
        gold_path = Path(golden) / f"{name}.json"
        if update:
            old = json.loads(gold_path.read_text()) if gold_path.exists() else {"keys": {}}
            keys = {}
            for key, default in TOLERANCES.items():
                value = _get(result, key)
                if value is None:
                    continue
                tol = {k: v for k, v in old["keys"].get(key, default).items() if k != "value"}
                if tol.get("at_most"):
                    value = max(AT_MOST_FLOOR, AT_MOST_FACTOR * max(abs(float(v)) for v in _flat(value)))
                keys[key] = {"value": value, **tol}
            gold_path.parent.mkdir(parents=True, exist_ok=True)
            gold_path.write_text(json.dumps({"spec": name, "keys": keys}, indent=1) + "\n")
            rows.append({"spec": name, "status": "updated", "differences": []})
        elif not gold_path.exists():
            rows.append({"spec": name, "status": "no golden", "differences": [f"no {gold_path}"]})
        else:
            try:
                gold = json.loads(gold_path.read_text())["keys"]
            except (OSError, ValueError, KeyError) as exc:
                raise ArtefactError(str(gold_path), f"is not a golden file ({exc})", "JSON with a 'keys' object (write one with --update)") from None
            diffs = [d for key, entry in gold.items() if (d := compare(key, _get(result, key), entry))]
            rows.append({"spec": name, "status": "differs" if diffs else "ok", "differences": diffs})
        if progress is not None:
            progress(rows[-1])
    return rows
