"""Stage order, staleness and caching: what ``ashc design`` and every stage command run.

A stage's artefact is *up to date* when it was written with the current schema version, from a spec whose keys
the stage reads (:func:`spec_keys`) have the same values (their SHA-256), and from upstream artefacts whose files
have the SHA-256s it recorded (and which are up to date themselves): adding a task or editing a scenario keeps the
design, editing ``abstract.p`` keeps the stabilise stage.  :func:`run` walks the stages a target needs in flow-chart order, reads those that are
up to date and recomputes the rest, writing each artefact atomically before the next stage starts.
A :class:`Folder` remembers what one command has read, written and judged, so that commands calling
:func:`run` several times (``check``, ``report``, ``regress``, ``sweep``) read and parse each file once.
"""

from __future__ import annotations

import dataclasses
import time
from collections.abc import Callable, Iterable
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ashc_cli.design.artefacts import SCHEMA_VERSION, Artefact, read_artefact, write_artefact
from ashc_cli.errors import ArtefactError, DesignError
from ashc_cli.numerics.boxsearch import work_budget
from ashc_cli.problem.influence import cone_model
from ashc_cli.problem.spec import Spec, keys_sha256
from ashc_cli.design.stages import DESIGN, ORDER

__all__ = ["STAGES", "DESIGN", "PRODUCTS", "Folder", "default_out", "artefact_path", "needed", "staleness", "check_upstream",
           "remove_leftovers", "register_product", "run", "headline", "DESIGN_KEYS", "spec_keys", "inputs_sha256", "made_from", "run_for_verdict", "load_all", "StageReport", "frozen_stages"]

#: Stage modules by name, in flow-chart order.
STAGES = {mod.NAME: mod for mod in ORDER}
#: Artefacts made by commands that are not flow-chart stages (they read a finished design), by name: modules
#: with ``NAME`` and ``summarise``, added by :func:`register_product` (:mod:`ashc_cli.products` registers its own).
PRODUCTS: dict = {}


def register_product(module) -> None:
    """Let :func:`load_all` and ``ashc summary`` know a product's artefact ``<module.NAME>.h5``.

    Parameters
    ----------
    module : module
        A product module with ``NAME`` and ``summarise``; registered in ``PRODUCTS`` under ``module.NAME``.
    """
    PRODUCTS[module.NAME] = module


@dataclass(frozen=True)
class StageReport:
    """What happened to one stage in a run (for progress lines)."""

    stage: str
    status: str          # "ran" or "up to date"
    seconds: float
    headline: str


#: Called with (stage, why it runs) just before a stage is computed (for a live progress display).
OnStart = Callable[[str, str], None]


def default_out(spec: Spec) -> Path:
    """Where a spec's artefacts go unless ``--out`` says otherwise: ``outputs/<name>``.

    Parameters
    ----------
    spec : Spec
        The spec (its ``name`` is read).

    Returns
    -------
    Path
        Relative to the working directory.
    """
    return Path("outputs") / spec.name


def artefact_path(out: str | Path, stage: str) -> Path:
    """The artefact file of a stage.

    Parameters
    ----------
    out : str or Path
        The artefact folder.
    stage : str
        The stage (or product) name.

    Returns
    -------
    Path
        ``<out>/<stage>.h5``.
    """
    return Path(out) / f"{stage}.h5"


@dataclass
class Folder:
    """An artefact folder as one command sees it: each artefact read at most once, each stage judged once.

    Attributes
    ----------
    path : Path
        The folder.
    arts : dict of str to Artefact
        Artefacts read from it or written to it by this command.
    reasons : dict of str to (str or None)
        :func:`staleness` of each stage judged so far (None: up to date).
    written : set of str
        Stages this command has (re)computed: a ``force`` does not compute them again.
    """

    path: Path
    arts: dict[str, Artefact] = field(default_factory=dict)
    reasons: dict[str, str | None] = field(default_factory=dict)
    written: set[str] = field(default_factory=set)

    def read(self, stage: str) -> Artefact:
        """The stage's artefact, read from its file the first time only."""
        if stage not in self.arts:
            self.arts[stage] = read_artefact(artefact_path(self.path, stage))
        return self.arts[stage]

    def wrote(self, stage: str, art: Artefact) -> None:
        """Record an artefact just written (with its provenance filled by ``write_artefact``)."""
        self.arts[stage], self.reasons[stage] = art, None
        self.written.add(stage)


def as_folder(out: str | Path | Folder) -> Folder:
    """A :class:`Folder` for ``out`` (itself if it is one already).

    Parameters
    ----------
    out : str, Path or Folder
        The artefact folder.

    Returns
    -------
    Folder
        A new, empty one unless ``out`` is already a Folder.
    """
    return out if isinstance(out, Folder) else Folder(Path(out))


def _upstream_of(name: str, spec: Spec | None = None) -> tuple[str, ...]:
    """The stages ``name`` reads: its module's ``upstream(spec)`` where it has one (stabilise reads the manifold for
    ``objective: min_gain``), else its ``UPSTREAM``."""
    mod = STAGES[name]
    fun = getattr(mod, "upstream", None)
    return tuple(fun(spec)) if fun is not None and spec is not None else tuple(mod.UPSTREAM)


#: The spec keys a design stage reads unless its module says otherwise (``reads(spec)`` or ``READS``): everything
#: but the scenarios, the task, the description and the units.
DESIGN_KEYS = ("parameters", "concrete", "stabilisability", "abstract", "interface", "proofs")


def spec_keys(name: str, spec: Spec) -> tuple[str, ...]:
    """The spec keys a stage reads: its module's ``reads(spec)``, else its ``READS``, else :data:`DESIGN_KEYS`.

    Parameters
    ----------
    name : str
        A stage.
    spec : Spec
        The spec (stabilise reads more for ``objective: min_gain``).

    Returns
    -------
    tuple of str
        Dotted spec keys.
    """
    mod = STAGES[name]
    fun = getattr(mod, "reads", None)
    return tuple(fun(spec)) if fun is not None else tuple(getattr(mod, "READS", DESIGN_KEYS))


def inputs_sha256(name: str, spec: Spec) -> str:
    """SHA-256 of the values of the spec keys a stage reads (stored with its artefact as ``inputs_sha256``).

    Parameters
    ----------
    name : str
        A stage.
    spec : Spec
        The spec.

    Returns
    -------
    str
    """
    return keys_sha256(spec, spec_keys(name, spec))


def made_from(spec: Spec, name: str, provenance: dict) -> bool:
    """Whether an artefact was made from this spec, as far as its stage or product reads it.

    A stage's artefact compares the keys it reads (``inputs_sha256``; one written before this digest existed, the
    whole spec); a product's (falsify, synthesize, ...) compares the whole spec.

    Parameters
    ----------
    spec : Spec
        The current spec.
    name : str
        The stage or product.
    provenance : dict
        The artefact's provenance.

    Returns
    -------
    bool
    """
    if name in STAGES and provenance.get("inputs_sha256"):
        return provenance["inputs_sha256"] == inputs_sha256(name, spec)
    return provenance.get("spec_sha256") == spec.sha256


def needed(targets: Iterable[str], spec: Spec | None = None) -> list[str]:
    """The targets and every stage upstream of them, in flow-chart order (an upstream stage always first).

    Parameters
    ----------
    targets : iterable of str
        Stage names.
    spec : Spec, optional
        Lets a stage's ``upstream(spec)`` choose what it reads; None uses every stage's ``UPSTREAM``.

    Returns
    -------
    list of str
    """
    want: set[str] = set()
    stack = list(targets)
    while stack:
        name = stack.pop()
        if name not in want:
            want.add(name)
            stack.extend(_upstream_of(name, spec))
    order: list[str] = []
    for name in STAGES:          # flow-chart order, with each stage moved after the stages it reads
        if name in want:
            _place(name, spec, want, order)
    return order


def _place(name: str, spec, want: set[str], order: list[str]) -> None:
    if name in order:
        return
    for up in _upstream_of(name, spec):
        if up in want:
            _place(up, spec, want, order)
    order.append(name)


def frozen_stages(frozen: bool | Iterable[str], targets: Iterable[str]) -> set[str]:
    """The stages :func:`run` must not recompute.

    Parameters
    ----------
    frozen : bool or iterable of str
        ``True``: every stage upstream of the targets (a stage command's ``--frozen``); ``False``: none; an
        iterable: exactly the stages it names (``design --frozen`` names them all).
    targets : iterable of str
        The stages asked for.

    Returns
    -------
    set of str
    """
    if isinstance(frozen, bool):
        targets = list(targets)
        return {name for name in needed(targets) if name not in targets} if frozen else set()
    return set(frozen)


def staleness(spec: Spec, out: str | Path | Folder, stage: str) -> str | None:
    """Why a stage's artefact is not up to date, or None if it is.

    Parameters
    ----------
    spec : Spec
        The current spec.
    out : str, Path or Folder
        The artefact folder (a :class:`Folder` remembers the artefacts read and the stages judged).
    stage : str
        The stage to examine.

    Returns
    -------
    str or None
        A reason (missing, unreadable, other spec, other schema, upstream changed) or None.
    """
    folder = as_folder(out)
    if stage in folder.reasons:
        return folder.reasons[stage]
    reason = None
    if not artefact_path(folder.path, stage).exists():
        reason = "no artefact yet"
    else:
        try:
            prov = folder.read(stage).provenance
        except ArtefactError:
            prov = None
            reason = "artefact unreadable"
        if prov is not None:
            if prov["schema_version"] != SCHEMA_VERSION:
                reason = f"artefact has schema {prov['schema_version']}, this ashc writes {SCHEMA_VERSION}"
            elif not made_from(spec, stage, prov):
                keys = ", ".join(spec_keys(stage, spec))
                reason = f"made from other values of the spec keys it reads ({keys})"
            else:
                for up in _upstream_of(stage, spec):
                    if staleness(spec, folder, up) is not None:
                        reason = f"upstream stage {up} is not up to date"
                        break
                    if prov["upstream"].get(up) != folder.read(up).provenance["sha256"]:
                        reason = f"upstream artefact {up}.h5 changed since"
                        break
    folder.reasons[stage] = reason
    return reason


def remove_leftovers(out: str | Path) -> list[Path]:
    """Delete temporary files a killed run left in the artefact folder (the artefacts themselves are whole).

    Parameters
    ----------
    out : str or Path
        The artefact folder (nothing happens if it is not a directory).

    Returns
    -------
    list of Path
        The files removed (``.<stage>.h5.*.tmp``).
    """
    removed = []
    folder = Path(out)
    if folder.is_dir():
        for tmp in folder.glob(".*.h5.*.tmp"):
            tmp.unlink(missing_ok=True)
            removed.append(tmp)
    return removed


def declared_names(spec: Spec) -> dict[str, list[str]]:
    """The names a spec declares (stored with every artefact, for ``ashc eval``).

    Parameters
    ----------
    spec : Spec
        The spec.

    Returns
    -------
    dict of str to list of str
        ``states``, ``inputs``, ``abstract_states`` and ``abstract_inputs``.
    """
    return {"states": list(spec.concrete.states), "inputs": list(spec.concrete.inputs),
            "abstract_states": list(spec.abstract.states), "abstract_inputs": list(spec.abstract.inputs)}


def check_upstream(spec: Spec, stage: str, arts: dict[str, Artefact]) -> None:
    """Refuse to run a stage on an upstream artefact made from another spec or schema.

    Parameters
    ----------
    spec : Spec
        The spec the stage is run with.
    stage : str
        The stage about to run.
    arts : dict of str to Artefact
        The artefacts so far; must hold every stage ``stage`` reads.

    Raises
    ------
    ArtefactError
        Naming the upstream stage to rerun.
    """
    for up in _upstream_of(stage, spec):
        prov = arts[up].provenance
        if prov.get("schema_version") != SCHEMA_VERSION:
            raise ArtefactError(f"{up}.h5", f"has schema {prov.get('schema_version')}, {stage} needs {SCHEMA_VERSION}", f"rerun `ashc {up} SPEC`")
        if not made_from(spec, up, prov):
            raise ArtefactError(f"{up}.h5", f"was made from another spec than the one {stage} is run with", f"rerun `ashc {up} SPEC`")


def run(
    spec: Spec,
    out: str | Path | Folder,
    targets: Iterable[str],
    *,
    force: bool = False,
    frozen: bool | Iterable[str] = False,
    on_stage: Callable[[StageReport], None] | None = None,
    numeric: bool | None = None,
    on_start: OnStart | None = None,
) -> dict[str, Artefact]:
    """Bring the target stages (and what they need) up to date.

    Parameters
    ----------
    spec : Spec
        The validated spec.
    out : str, Path or Folder
        The artefact folder; pass one :class:`Folder` to several calls so they read each artefact once.
    targets : iterable of str
        Stage names wanted.
    force : bool
        Recompute every needed stage that is not frozen, even if up to date (once per :class:`Folder`).
    frozen : bool or iterable of str
        Stages never to recompute: refuse (naming the stage to rerun) if one is not up to date.  ``True``
        freezes every stage upstream of the targets (the targets themselves may run); an iterable freezes
        exactly the stages it names (e.g. all of them, for a command that must only read the folder).
        A frozen stage is not recomputed by ``force`` either.
    on_stage : callable, optional
        Called with a :class:`StageReport` after each stage.
    numeric : bool, optional
        Force the numeric (True) or symbolic (False) paths; None chooses by size (``model.NUMERIC_THRESHOLD``).
    on_start : callable, optional
        Called with (stage, reason) just before a stage is computed (not for a stage read as up to date).

    Returns
    -------
    dict of str to Artefact
        The artefacts of every needed stage.

    Raises
    ------
    ArtefactError
        With ``frozen``, if a frozen stage is not up to date.
    """
    targets, folder = list(targets), as_folder(out)
    order = needed(targets, spec)
    fixed = frozen_stages(frozen, targets)
    model = dataclasses.replace(cone_model(spec), numeric_paths=numeric)
    remove_leftovers(folder.path)
    arts: dict[str, Artefact] = {}
    for name in order:
        mod = STAGES[name]
        start = time.perf_counter()
        if name in fixed:
            reason = staleness(spec, folder, name)
            if reason is not None:
                # a design stage is brought up to date with the rest of the design: `ashc design SPEC` is what a user runs
                command = "design" if name in DESIGN else name
                raise ArtefactError(f"{name}.h5", f"is not up to date ({reason})", f"run `ashc {command} SPEC` first, or drop --frozen")
        else:
            reason = "forced" if force and name not in folder.written else staleness(spec, folder, name)
        if reason is None:
            art = folder.read(name)
            status = "up to date"
        else:
            if on_start is not None:
                on_start(name, reason)
            check_upstream(spec, name, arts)
            reads = _upstream_of(name, spec)
            art = _computed(mod, model, {up: arts[up] for up in reads}, spec.proofs.max_boxes)
            write_artefact(artefact_path(folder.path, name), art, spec_sha256=spec.sha256, inputs_sha256=inputs_sha256(name, spec), spec_name=spec.name,
                           parameters=dict(spec.parameters), upstream={up: arts[up].provenance["sha256"] for up in reads},
                           names=declared_names(model.spec))
            folder.wrote(name, art)
            status = "ran"
        arts[name] = art
        if name == "manifold":
            model = _with_domain(model, art)
        if on_stage is not None:
            on_stage(StageReport(name, status, time.perf_counter() - start, headline(mod, art)))
    return arts


def _computed(mod, model, upstream: dict, max_boxes: int) -> Artefact:
    """A stage's artefact, its proofs bounded by ``max_boxes`` boxes per search, their work in ``meta["proof_work"]``."""
    with work_budget(max_boxes) as work:
        art = mod.run(model, upstream)
    art.meta["proof_work"] = {**work.as_meta(), **({"note": work.line()} if work.spent else {})}
    if model.beside is not None and mod is STAGES["stabilise"]:
        # the first box certifies the plant seen from y (issue 43): which states were left out, and why
        art.meta["left_out"] = {"states": list(model.beside.names), "note": model.beside.line()}
    return art


def headline(mod, art: Artefact) -> str:
    """A stage's one-line result, and where its proofs spent their box budget (``proofs.max_boxes``), the note saying so.

    Parameters
    ----------
    mod : module
        The stage's module (its ``headline``).
    art : Artefact
        Its artefact.

    Returns
    -------
    str
    """
    note = (art.meta.get("proof_work") or {}).get("note")
    left = (art.meta.get("left_out") or {}).get("note")
    return mod.headline(art) + (f"; {left}" if left else "") + (f"; {note}" if note else "")


def load_all(out: str | Path) -> dict[str, Artefact]:
    """Every artefact present in a folder, by stage (for summary and eval, which need no spec).

    Parameters
    ----------
    out : str or Path
        The artefact folder.

    Returns
    -------
    dict of str to Artefact
        The stages present, in flow-chart order, then the other ``*.h5`` files (products) by name.

    Raises
    ------
    ArtefactError
        If the folder holds no artefact at all.
    """
    # the stages in flow-chart order, then every product artefact (registered or not: falsify.h5, tradeoff.h5)
    products = sorted(p.stem for p in Path(out).glob("*.h5") if not p.name.startswith(".") and p.stem not in STAGES)
    arts = {name: read_artefact(artefact_path(out, name)) for name in (*STAGES, *products) if artefact_path(out, name).exists()}
    if not arts:
        raise ArtefactError(str(out), "holds no ashc artefact", "a folder written by `ashc design SPEC --out DIR`")
    return arts


def _with_domain(model, manifold: Artefact):
    """The model with V fixed: ``abstract.domain: auto`` takes the manifold stage's choice."""
    if model.V is not None:
        return model
    return dataclasses.replace(model, V=np.asarray(manifold.value("V"), dtype=float))


def design_model(spec: Spec, arts: dict[str, Artefact]):
    """The spec's model with V fixed, for work on a finished design (falsify).

    Parameters
    ----------
    spec : Spec
        The spec.
    arts : dict of str to Artefact
        The design's artefacts (``manifold`` is read for V when ``abstract.domain`` is ``auto``).

    Returns
    -------
    Model
    """
    return _with_domain(cone_model(spec), arts["manifold"])


def run_for_verdict(spec: Spec, out: str | Path | Folder, *, force: bool = False, frozen: bool = False,
                    on_stage: Callable[[StageReport], None] | None = None,
                    on_start: OnStart | None = None) -> tuple[dict[str, Artefact], tuple | None]:
    """Run the design stages one at a time, stopping at the first design condition that fails.

    Parameters
    ----------
    spec : Spec
        The validated spec.
    out : str, Path or Folder
        The artefact folder.
    force : bool
        Recompute every design stage (once per :class:`Folder`).
    frozen : bool
        Recompute nothing: refuse (:class:`~ashc_cli.errors.ArtefactError`, naming the stage) if a design stage
        is not up to date.
    on_stage : callable, optional
        Called with a :class:`StageReport` after each stage.
    on_start : callable, optional
        Called with (stage, reason) just before a stage is computed.

    Returns
    -------
    arts : dict
        The artefacts of the stages that succeeded.
    stopped : (stage, DesignError) or None
        Where and why the design stopped (for the Problem 1 verdict).
    """
    arts: dict[str, Artefact] = {}
    folder = as_folder(out)
    for stage in DESIGN:
        try:
            # One stage at a time, so a failing condition still leaves the verdict of the stages before it.
            arts.update(run(spec, folder, [stage], force=force, frozen=DESIGN if frozen else False, on_start=on_start,
                            on_stage=lambda report, stage=stage: on_stage(report) if on_stage and report.stage == stage else None))
        except DesignError as exc:
            return arts, (stage, exc)
    return arts, None
