"""HDF5 artefacts: one file per stage, written atomically, with provenance. The only module using h5py.

Layout of ``<out>/<stage>.h5``::

    /                 attrs: schema_version, stage, spec_sha256, inputs_sha256, spec_name, parameters (JSON), upstream (JSON {stage: sha256}),
                             names (JSON: the spec's declared states, inputs, abstract_states, abstract_inputs),
                             packages (JSON), created (UTC ISO 8601), ashc_version, meta (JSON: solver,
                             tolerances, integrator, ...)
    /values/<key>     a dataset per value (scalars, strings, arrays); keys may contain '/' (groups)
    /exprs/<name>     attrs shape; datasets srepr (exact, read back by a whitelist) and text (readable); or, for a
                      matrix kept as a Chebyshev series (:class:`~ashc_cli.numerics.chebyshev.Series`): attrs shape and
                      variables (JSON names), datasets coeffs and box (the series, exact) and text (one line); a
                      piecewise series (:class:`~ashc_cli.numerics.chebyshev.PiecewiseSeries`) adds breaks, its coeffs
                      one (rows, deg + 1) block per piece
    /checks/<name>    attrs value (float), passed (bool), description (str), evidence (proved | sampled | simulated)

A write goes to a temporary file in the same folder and is renamed over the target only once complete,
so an interrupted run leaves the previous artefact intact.

A series-backed matrix (``Artefact.set_series``) is stored as its coefficients, and its sympy formula is
built only when a reader asks for it (``Artefact.exprs`` builds it on first access): on the 512-state
ladder, printing and parsing p, dp/dxi and dp/dxi delta as formulas took longer than designing them.
"""

from __future__ import annotations

import hashlib
import json
import os
import tempfile
from dataclasses import dataclass, field
from datetime import datetime, UTC
from importlib import metadata
from pathlib import Path
from typing import Any

import h5py
import numpy as np
import sympy as sp

from ashc_cli import __version__
from ashc_cli.numerics.chebyshev import PiecewiseSeries, Series
from ashc_cli.errors import ArtefactError
from ashc_cli.problem.expr import from_srepr

__all__ = ["SCHEMA_VERSION", "Artefact", "Check", "write_artefact", "read_artefact", "file_sha256", "package_versions"]

#: Bumped whenever the layout or the meaning of a stored value changes; older artefacts are stale.
SCHEMA_VERSION = 4

_PACKAGES = ("numpy", "scipy", "sympy", "cvxpy", "clarabel", "h5py", "pydantic", "python-flint", "numba")
_STR = h5py.string_dtype()


@dataclass(frozen=True)
class Check:
    """A stage's check of its own result: a measured number and whether it passed.

    Attributes
    ----------
    value : float
        The measured number (a residual, a margin, a singular value, ...).
    passed : bool
        Whether the number meets the condition.
    description : str
        What was measured and against what threshold.
    evidence : str
        How the claim was established: ``proved`` (rigorous: ball arithmetic over the whole set, exact or
        symbolic arithmetic, or the vertex argument), ``sampled`` (on a finite set of points: it can miss a
        violation between them) or ``simulated`` (observed along simulated runs).
    """

    value: float
    passed: bool
    description: str
    evidence: str = "sampled"


class Exprs(dict):
    """The expression matrices of an artefact: a dict whose series-backed entries are built when first read.

    ``defer(name, build)`` registers a matrix by the function that builds it; reading it (``exprs[name]``,
    ``get``, ``values()``, ``items()``) builds it once.  ``name in exprs``, ``len`` and iteration over the
    names do not build anything.
    """

    def __init__(self, *args, **kwargs):
        super().__init__(*args, **kwargs)
        self._pending: dict = {}

    def defer(self, name: str, build) -> None:
        """Register ``name`` as built by ``build()`` on first access."""
        dict.pop(self, name, None)
        self._pending[name] = build

    def __missing__(self, key):
        if key in self._pending:
            value = self._pending.pop(key)()
            dict.__setitem__(self, key, value)
            return value
        raise KeyError(key)

    def __setitem__(self, key, value):
        self._pending.pop(key, None)
        dict.__setitem__(self, key, value)

    def __delitem__(self, key):
        if self._pending.pop(key, None) is None:
            dict.__delitem__(self, key)

    def update(self, *args, **kwargs):
        for key, value in dict(*args, **kwargs).items():
            self[key] = value

    def get(self, key, default=None):
        return self[key] if key in self else default

    def pop(self, key, *default):
        if key in self._pending:
            self[key]
        return dict.pop(self, key, *default)

    def __contains__(self, key) -> bool:
        return dict.__contains__(self, key) or key in self._pending

    def __iter__(self):
        yield from list(dict.keys(self)) + list(self._pending)

    def __len__(self) -> int:
        return dict.__len__(self) + len(self._pending)

    def keys(self):
        return list(self)

    def values(self):
        return [self[k] for k in self]

    def items(self):
        return [(k, self[k]) for k in self]

    def __repr__(self) -> str:
        return f"Exprs({sorted(self)})"


@dataclass
class Artefact:
    """What a stage produces: plain data, independent of how it is stored.

    Attributes
    ----------
    stage : str
        The stage's name.
    values : dict
        Numbers, strings and arrays; keys may contain '/' to group them.
    exprs : dict of str to sympy Matrix
        Symbolic results (with parameters as symbols); series-backed ones are built on first access.
    series : dict of str to Series
        The expressions kept numeric (``set_series``): their Chebyshev series, which the stages evaluate with
        numpy; ``exprs[name]`` is the series' formula.
    checks : dict of str to Check
        The stage's self-checks.
    meta : dict
        JSON-able facts about how the result was obtained (solver, tolerances, grids).
    provenance : dict
        Filled when written or read: spec_sha256, upstream hashes, created, packages, sha256 of the file.
    """

    stage: str
    values: dict[str, Any] = field(default_factory=dict)
    exprs: dict[str, sp.Matrix] = field(default_factory=Exprs)
    series: dict[str, Series] = field(default_factory=dict)
    #: The variables of each series' formula (sympy Symbols), by name.
    series_variables: dict[str, tuple] = field(default_factory=dict)
    checks: dict[str, Check] = field(default_factory=dict)
    meta: dict[str, Any] = field(default_factory=dict)
    provenance: dict[str, Any] = field(default_factory=dict)

    def expr(self, name: str) -> sp.Matrix:
        """A stored expression matrix by name (an :class:`ArtefactError` if it is not there)."""
        try:
            return self.exprs[name]
        except KeyError:
            raise ArtefactError(self.stage, f"artefact holds no expression '{name}'", f"one of {sorted(self.exprs)}") from None

    def set_series(self, name: str, series: Series | PiecewiseSeries, variables) -> None:
        """Store a matrix as a Chebyshev series in ``variables``; its formula (``exprs[name]``) is built when read."""
        if not isinstance(self.exprs, Exprs):
            self.exprs = Exprs(self.exprs)
        variables = tuple(variables)
        self.series[name] = series
        self.series_variables[name] = variables
        self.exprs.defer(name, lambda: series.to_sympy(list(variables)))

    def value(self, name: str):
        """A stored value by name (an :class:`ArtefactError` if it is not there)."""
        try:
            return self.values[name]
        except KeyError:
            raise ArtefactError(self.stage, f"artefact holds no value '{name}'", "an artefact written by this ashc version") from None


def package_versions() -> dict[str, str]:
    """Versions of the numerical packages a result depends on."""
    out = {}
    for name in _PACKAGES:
        try:
            out[name] = metadata.version(name)
        except metadata.PackageNotFoundError:  # pragma: no cover - all are dependencies
            out[name] = "absent"
    return out


def file_sha256(path: str | Path) -> str:
    """SHA-256 of a file's bytes.

    Parameters
    ----------
    path : str or Path
        The file, read in 1 MiB chunks.

    Returns
    -------
    str
        The digest as 64 lowercase hex digits.
    """
    digest = hashlib.sha256()
    with open(path, "rb") as fh:
        for chunk in iter(lambda: fh.read(1 << 20), b""):
            digest.update(chunk)
    return digest.hexdigest()


def _user_mode() -> int:
    """The mode a file created by the user gets: 0666 less their umask (read without changing it, from /proc where it
    is there; os.umask must set it to read it)."""
    try:
        for line in Path("/proc/self/status").read_text().splitlines():
            if line.startswith("Umask:"):
                return 0o666 & ~int(line.split()[1], 8)
    except OSError:
        pass
    mask = os.umask(0o022)
    os.umask(mask)
    return 0o666 & ~mask


def write_artefact(path: str | Path, art: Artefact, *, spec_sha256: str, spec_name: str, parameters: dict[str, float],
                   upstream: dict[str, str], names: dict[str, list[str]] | None = None, inputs_sha256: str = "") -> str:
    """Write an artefact atomically and return the new file's SHA-256.

    Parameters
    ----------
    path : str or Path
        Target file; its folder is created if needed.
    art : Artefact
        What to store.
    spec_sha256, spec_name : str
        The spec it was made from.
    parameters : dict of str to float
        The spec's parameter values (so stored formulas can be evaluated without the spec).
    upstream : dict of str to str
        SHA-256 of each upstream artefact file it was made from.
    names : dict of str to list of str, optional
        The spec's declared names (states, inputs, abstract_states, abstract_inputs), so a query can tell a
        declared name that a formula happens not to use from a misspelt one.
    inputs_sha256 : str, optional
        SHA-256 of the values of the spec keys the stage read (its staleness follows them; "" for a product).

    Returns
    -------
    str
        SHA-256 of the written file.
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    # The provenance read_artefact gives back (plus the file's sha256), so a written artefact needs no reading back.
    provenance = {"schema_version": SCHEMA_VERSION, "spec_sha256": spec_sha256, "inputs_sha256": inputs_sha256, "spec_name": spec_name, "parameters": parameters,
                  "upstream": upstream, "names": names or {}, "packages": package_versions(), "created": datetime.now(UTC).isoformat(timespec="seconds"),
                  "ashc_version": __version__}
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
    os.fchmod(fd, _user_mode())   # mkstemp's 0600 would hide the artefact from the user's group
    os.close(fd)
    try:
        with h5py.File(tmp, "w") as fh:
            fh.attrs["stage"] = art.stage
            for key, value in provenance.items():
                fh.attrs[key] = json.dumps(value, sort_keys=True) if isinstance(value, dict) else value
            fh.attrs["meta"] = json.dumps(art.meta, sort_keys=True, default=_json_default)
            values = fh.create_group("values")
            for key, value in art.values.items():
                _write_value(values, key, value)
            exprs = fh.create_group("exprs")
            for name in list(art.exprs):
                if name in art.series:
                    _write_series(exprs.create_group(name), art.series[name], art.series_variables[name])
                    continue
                matrix = sp.Matrix(art.exprs[name])
                grp = exprs.create_group(name)
                grp.attrs["shape"] = np.array(matrix.shape, dtype=np.int64)
                grp.create_dataset("srepr", data=np.array([sp.srepr(e) for e in matrix], dtype=object), dtype=_STR)
                grp.create_dataset("text", data=np.array([str(e) for e in matrix], dtype=object), dtype=_STR)
            checks = fh.create_group("checks")
            for name, chk in art.checks.items():
                grp = checks.create_group(name)
                grp.attrs["value"] = float(chk.value)
                grp.attrs["passed"] = bool(chk.passed)
                grp.attrs["description"] = chk.description
                grp.attrs["evidence"] = chk.evidence
        sha = file_sha256(tmp)
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise
    art.provenance = {**provenance, "sha256": sha}
    return sha


def _write_series(grp: h5py.Group, series: Series, variables) -> None:
    """A series-backed matrix: its coefficients and box (exact), its variables, and one line of text."""
    grp.attrs["shape"] = np.array(series.shape, dtype=np.int64)
    grp.attrs["variables"] = json.dumps([str(v) for v in variables])
    grp.create_dataset("coeffs", data=series.coeffs)
    grp.create_dataset("box", data=series.box)
    what = f"Chebyshev series of degree {series.degree} per axis on {series.box.tolist()}"
    if isinstance(series, PiecewiseSeries):
        grp.create_dataset("breaks", data=series.breaks)
        what = f"{len(series.pieces)} pieces of Chebyshev series of degree <= {series.degree} between the breaks {series.breaks.tolist()}"
    text = (f"{what} in {', '.join(str(v) for v in variables)} "
            f"(one per entry of the {series.shape[0]} x {series.shape[1]} matrix; the formula is rebuilt from these coefficients when read)")
    grp.create_dataset("text", data=np.array([text], dtype=object), dtype=_STR)


def _json_default(obj):
    if isinstance(obj, np.generic):
        return obj.item()
    if isinstance(obj, np.ndarray):
        return obj.tolist()
    raise TypeError(f"not JSON-able: {type(obj).__name__}")


def _write_value(group: h5py.Group, key: str, value: Any) -> None:
    if isinstance(value, str):
        group.create_dataset(key, data=value, dtype=_STR)
    elif isinstance(value, (list, tuple)) and value and all(isinstance(v, str) for v in value):
        group.create_dataset(key, data=np.array(value, dtype=object), dtype=_STR)
    else:
        group.create_dataset(key, data=np.asarray(value))


def read_artefact(path: str | Path) -> Artefact:
    """Read an artefact written by :func:`write_artefact`.

    Parameters
    ----------
    path : str or Path
        The HDF5 file.

    Returns
    -------
    Artefact
        With ``provenance`` holding the stored attributes and the file's SHA-256.

    Raises
    ------
    ArtefactError
        If the file is missing or is not a readable ashc artefact.
    """
    path = Path(path)
    if not path.is_file():
        raise ArtefactError(str(path), "no such artefact", "the output of the stage that writes it")
    try:
        with h5py.File(path, "r") as fh:
            attrs = dict(fh.attrs)
            art = Artefact(stage=str(attrs["stage"]))
            art.meta = json.loads(attrs.get("meta", "{}"))
            fh["values"].visititems(lambda name, obj: _read_value(art.values, name, obj))
            for name, grp in fh["exprs"].items():
                shape = tuple(int(s) for s in grp.attrs["shape"])
                if "coeffs" in grp:
                    # Variables are real symbols, as the model declares its states (model.state_symbol).
                    variables = [sp.Symbol(v, real=True) for v in json.loads(grp.attrs["variables"])]
                    if "breaks" in grp:
                        art.set_series(name, PiecewiseSeries.from_arrays(grp["coeffs"][()], grp["breaks"][()], shape), variables)
                    else:
                        art.set_series(name, Series(grp["coeffs"][()], grp["box"][()], shape), variables)
                    continue
                entries = [from_srepr(s.decode() if isinstance(s, bytes) else s, str(path)) for s in grp["srepr"][()]]
                art.exprs[name] = sp.Matrix(shape[0], shape[1], entries) if entries else sp.zeros(*shape)
            for name, grp in fh["checks"].items():
                art.checks[name] = Check(float(grp.attrs["value"]), bool(grp.attrs["passed"]), str(grp.attrs["description"]),
                                         str(grp.attrs.get("evidence", "sampled")))
    except ArtefactError:
        raise
    except (OSError, KeyError, ValueError, TypeError) as exc:
        raise ArtefactError(str(path), f"not a readable ashc artefact ({type(exc).__name__})", "a file written by ashc; rerun its stage") from None
    art.provenance = {
        "schema_version": int(attrs.get("schema_version", -1)),
        "spec_sha256": str(attrs.get("spec_sha256", "")),
        "inputs_sha256": str(attrs.get("inputs_sha256", "")),
        "spec_name": str(attrs.get("spec_name", "")),
        "parameters": json.loads(attrs.get("parameters", "{}")),
        "upstream": json.loads(attrs.get("upstream", "{}")),
        "names": json.loads(attrs.get("names", "{}")),
        "packages": json.loads(attrs.get("packages", "{}")),
        "created": str(attrs.get("created", "")),
        "ashc_version": str(attrs.get("ashc_version", "")),
        "sha256": file_sha256(path),
    }
    return art


def _read_value(store: dict, name: str, obj) -> None:
    if not isinstance(obj, h5py.Dataset):
        return
    data = obj[()]
    if isinstance(data, bytes):
        data = data.decode()
    elif isinstance(data, np.ndarray) and data.dtype == object:
        data = [d.decode() if isinstance(d, bytes) else d for d in data.tolist()]
    elif isinstance(data, np.generic):
        data = data.item()
    store[name] = data
