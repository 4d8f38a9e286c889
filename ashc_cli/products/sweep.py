"""``ashc sweep``: the design for every combination of parameter values, on a Dask cluster.

Each combination is one task: the spec with its ``parameters`` replaced is designed stage by stage (so a
failing design still has a verdict), optionally falsified, into its own folder ``<out>/sweep/<k>/``.  A
failing design is a result ("solved: no", with the reason), never an exception that stops the sweep.  By
default the tasks run on a local cluster of worker processes; ``--scheduler ADDRESS`` sends them to an
existing dask.distributed cluster.  The results are gathered into one HDF5 table (``sweep.h5``, written by
:mod:`ashc_cli.design.artefacts`) and a plot of the headline numbers against the first swept parameter.
"""

from __future__ import annotations

import itertools
import time
from pathlib import Path

import numpy as np

from ashc_cli.design.artefacts import Artefact, Check
from ashc_cli.errors import AshcError, SpecError
from ashc_cli.problem.spec import Spec

__all__ = ["parse_param", "combinations", "design_one", "sweep"]

NAME = "sweep"
HEADLINES = ("lambda", "dbar_q0", "gain")


def parse_param(text: str, spec: Spec) -> tuple[str, np.ndarray]:
    """``NAME=LO:HI:COUNT`` -> (name, values); NAME must be one of the spec's parameters.

    Parameters
    ----------
    text : str
        One ``--param`` value.
    spec : Spec
        The spec (its ``parameters`` are the names allowed).

    Returns
    -------
    name : str
    values : ndarray (COUNT,)
        ``np.linspace(LO, HI, COUNT)``.

    Raises
    ------
    SpecError
        Naming ``--param TEXT``: not of that form, not a parameter, LO or HI not finite, or COUNT not in 1 .. 10000.
    """
    where = f"--param {text}"
    name, sep, rest = text.partition("=")
    parts = rest.split(":")
    if not sep or len(parts) != 3:
        raise SpecError(where, "is not NAME=LO:HI:COUNT", "e.g. --param R_i=0.5:2:5")
    if name not in spec.parameters:
        raise SpecError(where, f"'{name}' is not a parameter of the spec", f"one of {', '.join(spec.parameters) or '(none declared)'}")
    try:
        lo, hi, count = float(parts[0]), float(parts[1]), int(parts[2])
    except ValueError:
        raise SpecError(where, "LO and HI must be numbers and COUNT an integer", "e.g. --param R_i=0.5:2:5") from None
    if not (np.isfinite(lo) and np.isfinite(hi)) or count < 1 or count > 10000:
        raise SpecError(where, f"LO = {lo}, HI = {hi}, COUNT = {count}", "finite bounds and 1 <= COUNT <= 10000")
    return name, np.linspace(lo, hi, count)


def combinations(axes: list[tuple[str, np.ndarray]]) -> list[dict[str, float]]:
    """Every combination of the swept values (the last parameter varies fastest).

    Parameters
    ----------
    axes : list of (str, ndarray)
        The swept parameters and their values (:func:`parse_param`).

    Returns
    -------
    list of dict of str to float
        One mapping name -> value per combination (the product of the axes' lengths).
    """
    names = [n for n, _ in axes]
    return [dict(zip(names, map(float, values))) for values in itertools.product(*[v for _, v in axes])]


def design_one(spec_json: dict, params: dict[str, float], out: str, falsify_runs: int) -> dict:
    """One task: design (and optionally falsify) the spec with these parameter values.

    Runs in a worker process; returns plain data.  Every ashc error becomes a failed row.

    Parameters
    ----------
    spec_json : dict
        The base spec, ``Spec.model_dump(mode="json")``.
    params : dict of str to float
        The parameter values that replace the spec's (one of :func:`combinations`).
    out : str
        The artefact folder of this combination.
    falsify_runs : int
        Runs of ``ashc falsify`` when the design is solved (0: none).

    Returns
    -------
    dict
        ``params``, ``solved``, ``verdict``, ``lambda``, ``dbar_q0``, ``gain``, ``falsify_ratio`` (NaN where not reached),
        ``error`` (the reason the design stopped, "" if none) and ``seconds``.
    """
    from ashc_cli.design.pipeline import Folder, run_for_verdict
    from ashc_cli.products.campaign import run_falsify
    from ashc_cli.problem.spec import Spec
    from ashc_cli.design.verdict import verdict

    start = time.perf_counter()
    row = {"params": params, "solved": False, "verdict": "fails", "lambda": np.nan, "dbar_q0": np.nan, "gain": np.nan,
           "falsify_ratio": np.nan, "error": ""}
    try:
        data = dict(spec_json)
        data["parameters"] = {**data.get("parameters", {}), **params}
        spec = Spec.model_validate(data)
        folder = Folder(Path(out))  # the falsify run below reuses the artefacts the design read or wrote
        arts, stopped = run_for_verdict(spec, folder)
        found = verdict(arts, stopped)
        row["solved"], row["verdict"] = found.solved, found.kind
        if "stabilise" in arts:
            row["lambda"] = float(arts["stabilise"].value("lambda"))
        if "bound" in arts:
            row["dbar_q0"] = float(arts["bound"].value("dbar_q0"))
            row["gain"] = float(arts["bound"].value("gain"))
        if stopped is not None:
            row["error"] = stopped[1].line()
        elif falsify_runs > 0:
            row["falsify_ratio"] = float(run_falsify(spec, folder, falsify_runs)[1].value("max_ratio"))
    except AshcError as exc:
        row["error"] = exc.line()
    except Exception as exc:  # a bug in one combination must not stop the sweep; it is recorded
        row["error"] = f"internal: {type(exc).__name__}: {exc}"
    row["seconds"] = time.perf_counter() - start
    return row


def sweep(spec: Spec, axes: list[tuple[str, np.ndarray]], out: Path, scheduler: str | None = None, workers: int = 2,
          falsify_runs: int = 0, progress=None) -> Artefact:
    """Run every combination on Dask and gather the results.

    Parameters
    ----------
    spec : Spec
        The base spec.
    axes : list of (name, values)
        The swept parameters (:func:`parse_param`).
    out : Path
        Folder: each combination designs into ``out/sweep/<k>``.
    scheduler : str, optional
        Address of an existing dask.distributed scheduler; otherwise a local cluster of ``workers`` processes.
    workers : int
        Worker processes of the local cluster.
    falsify_runs : int
        Runs of ``ashc falsify`` per solved combination (0: none).
    progress : callable, optional
        Called with each finished row.

    Returns
    -------
    Artefact
        The table: one row per combination (parameters, lambda, dbar_q0, gain, solved, falsify ratio, seconds, error).
    """
    try:
        from dask.distributed import Client, LocalCluster, as_completed
    except ImportError:
        raise SpecError("sweep", "needs dask.distributed, which is not installed", "pip install 'ashc[sweep]'") from None

    combos = combinations(axes)
    spec_json = spec.model_dump(mode="json")
    folders = [str(Path(out) / "sweep" / str(k)) for k in range(len(combos))]
    cluster = None
    start = time.perf_counter()
    if scheduler is None:
        cluster = LocalCluster(n_workers=workers, threads_per_worker=1, processes=True, dashboard_address=None)
        client = Client(cluster)
    else:
        try:
            client = Client(scheduler, timeout=5)
        except (OSError, TimeoutError) as exc:
            raise SpecError("--scheduler", f"no dask scheduler answers at {scheduler} ({exc})", "the address of a running dask.distributed scheduler") from None
    try:
        futures = client.map(design_one, [spec_json] * len(combos), combos, folders, [falsify_runs] * len(combos), pure=False)
        index = {f.key: k for k, f in enumerate(futures)}
        rows: list[dict | None] = [None] * len(combos)
        for future in as_completed(futures):
            rows[index[future.key]] = future.result()
            if progress is not None:
                progress(rows[index[future.key]])
        n_workers = len(client.scheduler_info().get("workers", {}))
    finally:
        client.close()
        if cluster is not None:
            cluster.close()

    art = Artefact(stage=NAME, meta={"scheduler": scheduler or f"local cluster, {workers} processes", "workers": n_workers,
                                      "parameters": [n for n, _ in axes], "falsify_runs": falsify_runs})
    art.values.update({
        "parameter_values": np.array([[r["params"][n] for n, _ in axes] for r in rows], dtype=float),
        "solved": np.array([r["solved"] for r in rows], dtype=bool),
        "verdict": [r.get("verdict", "fails") for r in rows],
        "lambda": np.array([r["lambda"] for r in rows], dtype=float),
        "dbar_q0": np.array([r["dbar_q0"] for r in rows], dtype=float),
        "gain": np.array([r["gain"] for r in rows], dtype=float),
        "falsify_ratio": np.array([r["falsify_ratio"] for r in rows], dtype=float),
        "seconds": np.array([r["seconds"] for r in rows], dtype=float),
        "error": [r["error"] or "none" for r in rows],
        "wall_seconds": time.perf_counter() - start,
    })
    solved = int(art.values["solved"].sum())
    art.checks["combinations_solved"] = Check(float(solved), True, f"combinations for which Problem 1 is solved (of {len(rows)})")
    return art


def plot(art: Artefact, path: Path) -> Path:
    """lambda, dbar_q0 and the gain G against the first swept parameter (failed combinations marked).

    Parameters
    ----------
    art : Artefact
        The sweep artefact (of :func:`sweep`).
    path : Path
        The file; its suffix gives the format (:func:`ashc_cli.outputs.plots.save`).

    Returns
    -------
    Path
        ``path``.
    """
    from ashc_cli.outputs.plots import COLUMN_WIDTH, STYLE, plt, save

    v = art.values
    x = np.asarray(v["parameter_values"])[:, 0]
    solved = np.asarray(v["solved"])
    with plt.rc_context(STYLE):
        fig, axes = plt.subplots(len(HEADLINES), 1, figsize=(COLUMN_WIDTH, 4.5), sharex=True)
        for ax, key in zip(axes, HEADLINES):
            y = np.asarray(v[key])
            ax.plot(x[solved], y[solved], "o", markersize=3, label="solved")
            if (~solved).any():
                ax.plot(x[~solved], np.where(np.isfinite(y[~solved]), y[~solved], np.nanmin(y) if np.isfinite(y).any() else 0), "x", color="C3", label="not solved")
            ax.set_ylabel(key)
        axes[0].legend(loc="best")
        axes[-1].set_xlabel(art.meta["parameters"][0])
        fig.tight_layout()
        return save(fig, path)
