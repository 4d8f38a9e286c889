"""Tests of stage order and caching (ashc_cli.design.pipeline)."""

import shutil

import pytest

from ashc_cli.design import pipeline
from ashc_cli.products import campaign
from ashc_cli.design.artefacts import Artefact, read_artefact, write_artefact
from ashc_cli.errors import ArtefactError
from ashc_cli.design.pipeline import DESIGN, Folder, needed, run, run_for_verdict, staleness
from ashc_cli.problem.spec import load_spec, parse_spec_text

from .conftest import CUK, CUK_PAPER_M


def test_needed_is_flow_chart_order():
    assert needed(["kappa"]) == ["manifold", "kappa"]
    assert needed(["bound"]) == ["stabilise", "manifold", "kappa", "inverse", "delta", "bound"]
    assert needed(["simulate"])[-1] == "simulate"


def test_reruns_exactly_the_stale_stages(paper_out, tmp_path):
    spec = load_spec(CUK_PAPER_M)
    out = tmp_path / "out"
    shutil.copytree(paper_out, out)
    assert all(staleness(spec, out, s) is None for s in DESIGN)
    seen = []
    run(spec, out, DESIGN, on_stage=lambda r: seen.append((r.stage, r.status)))
    assert {status for _, status in seen} == {"up to date"}

    # A changed delta leaves stabilise alone (it reads the plant and the stabilisability keys) and reruns the rest.
    text = CUK_PAPER_M.read_text().replace('delta: "((xi - 1)**2 + G_L*R_i*xi**2)**2"', 'delta: "1"')
    spec2 = parse_spec_text(text)
    assert staleness(spec2, out, "delta").startswith("made from other values of the spec keys it reads (parameters, concrete, ")
    assert staleness(spec2, out, "stabilise") is None
    seen.clear()
    arts = run(spec2, out, DESIGN, on_stage=lambda r: seen.append((r.stage, r.status)))
    assert seen == [("stabilise", "up to date")] + [(s, "ran") for s in DESIGN[1:]]
    assert abs(arts["bound"].values["dbar_q0_sampled"] - arts["bound"].values["dbar_q0_identity"]) < 1e-9

    # Rewriting an upstream artefact with other content makes its downstream stale, not its upstream.  (A rerun
    # within the same second writes the same bytes, which rightly leaves the downstream up to date, so the
    # content is changed on purpose here.)
    man = read_artefact(out / "manifold.h5")
    man.meta["note"] = "rewritten by the test"
    prov = man.provenance
    write_artefact(out / "manifold.h5", man, spec_sha256=prov["spec_sha256"], spec_name=prov["spec_name"],
                   parameters=prov["parameters"], upstream=prov["upstream"], inputs_sha256=prov["inputs_sha256"])
    assert staleness(spec2, out, "stabilise") is None
    assert staleness(spec2, out, "kappa") == "upstream artefact manifold.h5 changed since"
    assert staleness(spec2, out, "bound") == "upstream artefact manifold.h5 changed since"
    assert staleness(spec2, out, "delta") == "upstream artefact manifold.h5 changed since"
    assert staleness(spec2, out, "inverse") == "upstream artefact manifold.h5 changed since"


def test_a_task_or_a_scenario_keeps_the_design_and_abstract_p_keeps_stabilise(paper_out, tmp_path):
    # Issue 39: adding a task re-ran the whole design (a 45 s stabilise stage on a levitation plant); each stage now
    # follows the spec keys it reads.
    out = tmp_path / "out"
    shutil.copytree(paper_out, out)
    text = CUK_PAPER_M.read_text()
    tasked = parse_spec_text(text.replace("t_final: 30.0", "t_final: 20.0").replace("units: {t: s, y: V}", "units: {t: s}")
                             .replace("description: DC-to-DC", "description: another DC-to-DC")
                             + "\ntask: {horizon: 30, always: [[-120, 0]], reach: [{set: [[-82, -78]], by: 25}]}\n")
    assert tasked.sha256 != load_spec(CUK_PAPER_M).sha256
    seen = []
    run(tasked, out, DESIGN, on_stage=lambda r: seen.append((r.stage, r.status)))
    assert seen == [(s, "up to date") for s in DESIGN]
    assert staleness(tasked, out, "simulate") is not None          # the scenario and the task are what simulate reads
    # abstract.p written out by hand: the abstraction reruns, the contraction certificate is kept
    p_text = text.replace("  delta:", '  p: ["0", "0", "0", "xi"]\n  delta:', 1)
    assert staleness(parse_spec_text(p_text), out, "stabilise") is None
    assert staleness(parse_spec_text(p_text), out, "manifold").startswith("made from other values")
    # a budget of the proofs, the plant or the stabilisability keys: stabilise reruns
    for edit in ("\nproofs: {max_boxes: 30000}\n", None):
        other = text + edit if edit else text.replace("decay_rate:", "decay_rate: 1.9 #", 1)
        assert staleness(parse_spec_text(other), out, "stabilise") is not None, edit


def test_an_artefact_without_the_inputs_digest_follows_the_whole_spec(paper_out, tmp_path):
    # Artefacts written before the per-key digest existed are judged as before: by the whole spec's SHA-256.
    out = tmp_path / "out"
    shutil.copytree(paper_out, out)
    spec = load_spec(CUK_PAPER_M)
    art = read_artefact(out / "stabilise.h5")
    prov = art.provenance
    write_artefact(out / "stabilise.h5", art, spec_sha256=prov["spec_sha256"], spec_name=prov["spec_name"],
                   parameters=prov["parameters"], upstream=prov["upstream"])
    assert read_artefact(out / "stabilise.h5").provenance["inputs_sha256"] == ""
    assert staleness(spec, out, "stabilise") is None
    tasked = parse_spec_text(CUK_PAPER_M.read_text() + "\ntask: {horizon: 30, reach: [{set: [[-82, -78]], by: 25}]}\n")
    assert staleness(tasked, out, "stabilise") == "made from other values of the spec keys it reads (parameters, concrete, stabilisability, proofs, abstract.states, abstract.inputs)"


def test_min_gain_stabilise_reads_the_abstraction():
    base = CUK_PAPER_M.read_text()
    spec = parse_spec_text(base)
    assert "abstract" not in pipeline.spec_keys("stabilise", spec)
    gain = parse_spec_text(CUK.read_text().replace("decay_rate:", "objective: min_gain\n  decay_rate:", 1))
    assert {"abstract", "interface"} <= set(pipeline.spec_keys("stabilise", gain))
    assert pipeline.spec_keys("manifold", spec) == pipeline.DESIGN_KEYS
    assert {"simulate", "task"} <= set(pipeline.spec_keys("simulate", spec))


def test_corrupt_artefact_is_stale(paper_out, tmp_path):
    spec = load_spec(CUK_PAPER_M)
    out = tmp_path / "out"
    shutil.copytree(paper_out, out)
    (out / "kappa.h5").write_bytes(b"garbage")
    assert staleness(spec, out, "kappa") == "artefact unreadable"
    assert staleness(spec, out, "manifold") is None


def test_a_folder_reads_each_artefact_once(paper_out, tmp_path, monkeypatch):
    # check/report/regress run the design one stage at a time: each file is still read (and parsed) once.
    spec = load_spec(CUK_PAPER_M)
    out = tmp_path / "out"
    shutil.copytree(paper_out, out)
    reads = []
    monkeypatch.setattr(pipeline, "read_artefact", lambda path: reads.append(path.name) or read_artefact(path))
    arts, stopped = run_for_verdict(spec, out)
    assert stopped is None and set(arts) == set(DESIGN)
    assert sorted(reads) == sorted(f"{s}.h5" for s in DESIGN)

    # force: every stage recomputed (and written) once per Folder, not once per later stage that needs it.
    written = []
    monkeypatch.setattr(pipeline, "write_artefact", lambda path, art, **kw: written.append(path.name) or write_artefact(path, art, **kw))
    run_for_verdict(spec, Folder(out), force=True)
    assert written == [f"{s}.h5" for s in DESIGN]


def test_frozen_stages_and_force(paper_out, tmp_path):
    spec = load_spec(CUK_PAPER_M)
    out = tmp_path / "out"
    shutil.copytree(paper_out, out)
    # A collection freezes exactly those stages, targets included: nothing is recomputed.
    run(spec, out, DESIGN, frozen=DESIGN)  # all up to date: fine
    (out / "delta.h5").unlink()
    with pytest.raises(ArtefactError, match=r"delta.h5: is not up to date \(no artefact yet\); expected run `ashc design SPEC` first"):
        run(spec, Folder(out), DESIGN, frozen=DESIGN)
    with pytest.raises(ArtefactError, match="delta.h5"):
        run_for_verdict(spec, Folder(out), frozen=True)
    assert not (out / "delta.h5").exists()
    # frozen=True with force: the target is recomputed, its upstream only read (this used to refuse the
    # upstream as "not up to date (forced)").
    seen = []
    run(spec, out, ["kappa"], force=True, frozen=True, on_stage=lambda r: seen.append((r.stage, r.status)))
    assert seen == [("manifold", "up to date"), ("kappa", "ran")]
    assert pipeline.frozen_stages(True, ["bound"]) == set(DESIGN) - {"bound"}
    assert pipeline.frozen_stages(False, ["bound"]) == set()
    assert pipeline.frozen_stages(["stabilise"], ["bound"]) == {"stabilise"}


def test_on_start_is_called_before_each_stage_computed(paper_out, tmp_path):
    spec = load_spec(CUK_PAPER_M)
    out = tmp_path / "out"
    shutil.copytree(paper_out, out)
    (out / "delta.h5").unlink()
    events = []
    run(spec, out, DESIGN, on_start=lambda stage, reason: events.append(("start", stage, reason)),
        on_stage=lambda r: events.append(("done", r.stage, r.status)))
    started = [e for e in events if e[0] == "start"]
    assert started[0] == ("start", "delta", "no artefact yet")
    assert {stage for _, stage, _ in started} <= {"delta", "bound"}  # bound only if delta.h5 came out different
    for event in started:  # each start comes just before its stage's report
        assert events[events.index(event) + 1] == ("done", event[1], "ran")


def test_falsify_differs_names_the_setting(paper_design, paper_spec):
    stored = Artefact(stage="falsify", meta={"runs": 64, "seed": 0}, values={"t_final": 10.0})
    stored.provenance = {"spec_sha256": paper_spec.sha256,
                         "upstream": {up: paper_design[up].provenance["sha256"] for up in campaign.FALSIFY_UPSTREAM}}
    t_default = campaign.falsify_t_final(paper_spec, None)
    assert campaign.falsify_differs(paper_spec, paper_design, stored) is None           # nothing asked: any run will do
    assert campaign.falsify_differs(paper_spec, paper_design, stored, 64, 0) is None
    assert campaign.falsify_differs(paper_spec, paper_design, stored, 32, 0) == "made with --runs 64, not 32"
    assert campaign.falsify_differs(paper_spec, paper_design, stored, 32, 1) == "made with --runs 64, not 32, --seed 0, not 1"
    assert campaign.falsify_differs(paper_spec, paper_design, stored, t_final=10.0, t_final_given=True) is None
    assert campaign.falsify_differs(paper_spec, paper_design, stored, t_final=2.0, t_final_given=True) == "made with --t-final 10, not 2"
    if t_default != 10.0:
        assert campaign.falsify_differs(paper_spec, paper_design, stored, t_final_given=True) == f"made with --t-final 10, not {t_default:g}"
    stored.provenance["upstream"]["bound"] = "0" * 64
    assert campaign.falsify_differs(paper_spec, paper_design, stored, 64, 0) == "made for an earlier design (bound.h5 changed since)"
    stored.provenance["spec_sha256"] = "other"
    assert campaign.falsify_differs(paper_spec, paper_design, stored) == "made from another spec"
