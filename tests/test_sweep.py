"""Tests of ashc sweep: parameter studies on Dask (a local cluster, and an explicit scheduler address)."""

import json

import numpy as np
import pytest

from ashc_cli.design.artefacts import read_artefact
from ashc_cli.problem.spec import load_spec
from ashc_cli.products.sweep import combinations, parse_param
from ashc_cli.errors import SpecError

from .conftest import SPECS, ashc

BOOST = SPECS / "boost_converter.yaml"


@pytest.mark.slow
def test_local_cluster_sweep_records_failures_and_goes_on(tmp_path):
    # r = 0.05 and 0.1 design; at r = 2 kappa turns inside V (p not injective): recorded, not fatal.
    proc = ashc("sweep", str(BOOST), "--param", "r=0.05:0.1:2", "--param", "R=10:10:1", "--out", str(tmp_path), "--json")
    assert proc.returncode == 0, proc.stderr
    res = json.loads(proc.stdout)
    assert res["combinations"] == 2 and res["solved"] == 2 and res["workers"] == 2
    proc = ashc("sweep", str(BOOST), "--param", "r=0.1:2:2", "--out", str(tmp_path / "b"), "--json")
    assert proc.returncode == 0, proc.stderr
    table = read_artefact(tmp_path / "b" / "sweep.h5").values
    assert table["solved"].tolist() == [True, False]
    assert "not injective" in table["error"][1]
    assert np.isfinite(table["gain"][0]) and np.isnan(table["gain"][1])
    assert (tmp_path / "b" / "plots" / "sweep.png").stat().st_size > 10_000


def test_sweep_on_an_explicit_scheduler(tmp_path):
    distributed = pytest.importorskip("distributed")
    with distributed.LocalCluster(n_workers=1, threads_per_worker=1, processes=True, host="127.0.0.1", dashboard_address=None) as cluster:
        proc = ashc("sweep", str(BOOST), "--param", "r=0.05:0.1:2", "--scheduler", cluster.scheduler_address, "--out", str(tmp_path), "--json")
    assert proc.returncode == 0, proc.stderr
    res = json.loads(proc.stdout)
    assert res["solved"] == 2 and res["workers"] == 1
    values = read_artefact(tmp_path / "sweep.h5").values["parameter_values"][:, 0]
    assert values.tolist() == [0.05, 0.1]


def test_param_parsing():
    spec = load_spec(BOOST)
    name, values = parse_param("r=0:1:3", spec)
    assert name == "r" and values.tolist() == [0.0, 0.5, 1.0]
    assert len(combinations([("a", np.array([1.0, 2.0])), ("b", np.array([3.0, 4.0, 5.0]))])) == 6
    for bad, fragment in (("q=0:1:3", "not a parameter"), ("r=0:1", "NAME=LO:HI:COUNT"), ("r=a:1:3", "must be numbers"), ("r=0:1:0", "COUNT")):
        with pytest.raises(SpecError, match=fragment):
            parse_param(bad, spec)


def test_unreachable_scheduler_is_a_clear_error(tmp_path):
    proc = ashc("sweep", str(BOOST), "--param", "r=0.1:0.1:1", "--scheduler", "tcp://127.0.0.1:9", "--out", str(tmp_path))
    assert proc.returncode == 2
    assert "no dask scheduler answers" in proc.stderr


def test_without_dask_the_sweep_says_which_extra_to_install(monkeypatch, tmp_path):
    # dask and distributed are the `sweep` extra: without them only `ashc sweep` refuses, with a one-line error
    import builtins

    from ashc_cli.products import sweep as sweep_mod
    real = builtins.__import__

    def no_dask(name, *args, **kwargs):
        if name.split(".")[0] in ("dask", "distributed"):
            raise ImportError(name)
        return real(name, *args, **kwargs)

    monkeypatch.setattr(builtins, "__import__", no_dask)
    spec = load_spec(SPECS / "boost_converter.yaml")
    with pytest.raises(SpecError, match=r"needs dask.distributed.*ashc\[sweep\]"):
        sweep_mod.sweep(spec, [parse_param("r=0.05:2:2", spec)], tmp_path)
