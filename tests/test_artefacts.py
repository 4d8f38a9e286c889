"""Tests of HDF5 artefacts (ashc_cli.design.artefacts): round trip, provenance, atomic writes."""

import h5py
import numpy as np
import pytest
import sympy as sp

from ashc_cli.design import artefacts
from ashc_cli.design.artefacts import SCHEMA_VERSION, Artefact, Check, read_artefact, write_artefact
from ashc_cli.errors import ArtefactError


def sample():
    x = sp.Symbol("x", real=True)
    E = sp.Symbol("E", positive=True)
    art = Artefact(stage="demo", meta={"solver": "none", "tol": 1e-9})
    art.values.update({"M": np.eye(2), "lambda": 2.0, "name": "cuk", "tags": ["a", "b"], "group/t": np.arange(3.0)})
    art.exprs["p"] = sp.Matrix([E * x / (x - 1), sp.sqrt(E**2 - x**2)])
    art.checks["margin"] = Check(-0.5, True, "a margin")
    return art


def write(path, art):
    return write_artefact(path, art, spec_sha256="abc", spec_name="s", parameters={"E": 12.0}, upstream={"up": "123"})


def test_round_trip(tmp_path):
    path = tmp_path / "demo.h5"
    sha = write(path, sample())
    back = read_artefact(path)
    assert back.stage == "demo"
    assert np.array_equal(back.values["M"], np.eye(2)) and back.values["lambda"] == 2.0
    assert back.values["name"] == "cuk" and back.values["tags"] == ["a", "b"]
    assert np.array_equal(back.values["group/t"], [0.0, 1.0, 2.0])
    assert back.exprs["p"] == sample().exprs["p"]  # exact, assumptions included
    assert back.checks["margin"] == Check(-0.5, True, "a margin")
    prov = back.provenance
    assert prov["sha256"] == sha and prov["spec_sha256"] == "abc" and prov["upstream"] == {"up": "123"}
    assert prov["schema_version"] == SCHEMA_VERSION and prov["parameters"] == {"E": 12.0}
    assert "numpy" in prov["packages"] and prov["created"]
    with h5py.File(path) as fh:  # the readable form is there too
        assert fh["exprs/p/text"][0].decode() == "E*x/(x - 1)"


def test_crash_during_write_keeps_previous_artefact(tmp_path, monkeypatch):
    path = tmp_path / "demo.h5"
    write(path, sample())
    before = path.read_bytes()

    def boom(*a, **k):
        raise RuntimeError("disk full")

    monkeypatch.setattr(artefacts, "_write_value", boom)
    with pytest.raises(RuntimeError):
        write(path, sample())
    assert path.read_bytes() == before
    assert read_artefact(path).values["lambda"] == 2.0
    assert [p.name for p in tmp_path.iterdir()] == ["demo.h5"]  # no temporary file left behind


def test_unreadable_and_missing(tmp_path):
    bad = tmp_path / "bad.h5"
    bad.write_bytes(b"not hdf5")
    with pytest.raises(ArtefactError, match="not a readable ashc artefact"):
        read_artefact(bad)
    with pytest.raises(ArtefactError, match="no such artefact"):
        read_artefact(tmp_path / "none.h5")


def test_tampered_expression_is_not_executed(tmp_path):
    path = tmp_path / "demo.h5"
    write(path, sample())
    with h5py.File(path, "a") as fh:
        fh["exprs/p/srepr"][0] = "__import__('os').system('touch pwned')"
    with pytest.raises(ArtefactError):
        read_artefact(path)
    assert not (tmp_path / "pwned").exists()


def test_series_backed_exprs_are_stored_as_coefficients_and_built_when_read(tmp_path, monkeypatch):
    from ashc_cli.numerics import chebyshev

    xi = sp.Symbol("xi", real=True)
    box = np.array([[0.0, 0.6]])
    z = chebyshev.nodes(box, 12)
    series = chebyshev.Series.column(chebyshev.fit(np.stack([np.exp(z[0]), 1 / (2 - z[0])]), box, z, 10), box)
    art = sample()
    art.set_series("q", series, [xi])
    assert "q" in art.exprs and len(art.exprs) == 2 and sorted(art.exprs) == ["p", "q"]
    path = tmp_path / "demo.h5"
    write(path, art)
    with h5py.File(path) as fh:       # the coefficients, exactly; no formula printed
        assert "srepr" not in fh["exprs/q"] and np.array_equal(fh["exprs/q/coeffs"][()], series.coeffs)
        assert fh["exprs/q/text"][0].decode().startswith("Chebyshev series of degree 10")

    expected = series.to_sympy([xi])
    built = []
    to_sympy = chebyshev.Series.to_sympy
    monkeypatch.setattr(chebyshev.Series, "to_sympy", lambda self, v: built.append(1) or to_sympy(self, v))
    back = read_artefact(path)
    assert np.array_equal(back.series["q"].coeffs, series.coeffs) and np.array_equal(back.series["q"].box, box)
    assert back.exprs["p"] == sample().exprs["p"] and "q" in back.exprs and built == []    # not built until asked for
    assert back.expr("q") == expected and built == [1]
    assert back.exprs["q"].free_symbols == {xi} and back.exprs.get("q") is back.exprs["q"] and built == [1]
    assert dict(back.exprs.items()).keys() == {"p", "q"}


def test_a_piecewise_series_is_stored_and_read_back_exactly(tmp_path):
    import numpy as np
    import sympy as sp

    from ashc_cli.design.artefacts import Artefact, read_artefact, write_artefact
    from ashc_cli.numerics import chebyshev

    pieces = tuple(chebyshev.Series.column(np.random.default_rng(k).normal(size=(2, 6)), [[lo, hi]]) for k, (lo, hi) in enumerate([(0, 1), (1, 2.5)]))
    s = chebyshev.PiecewiseSeries(pieces)
    art = Artefact(stage="manifold")
    xi = sp.Symbol("xi", real=True)
    art.set_series("p", s, [xi])
    write_artefact(tmp_path / "manifold.h5", art, spec_sha256="0" * 64, spec_name="t", parameters={}, upstream={}, names={})
    back = read_artefact(tmp_path / "manifold.h5").series["p"]
    assert isinstance(back, chebyshev.PiecewiseSeries) and np.array_equal(back.breaks, s.breaks)
    z = np.linspace(-0.5, 3, 71)
    assert np.array_equal(back(z), s(z))


@pytest.mark.parametrize("umask, mode", [(0o022, 0o644), (0o077, 0o600), (0o002, 0o664)])
def test_an_artefact_gets_the_mode_the_users_umask_gives(tmp_path, umask, mode):
    import os
    import stat

    old = os.umask(umask)
    try:
        write(tmp_path / "a.h5", Artefact(stage="stabilise"))
    finally:
        os.umask(old)
    assert stat.S_IMODE((tmp_path / "a.h5").stat().st_mode) == mode   # not mkstemp's 0600
