"""Tests of stage order and caching (ashc_cli.design.pipeline)."""

import shutil

import pytest

from ashc_cli.design import pipeline
from ashc_cli.products import campaign
from ashc_cli.design.artefacts import Artefact, read_artefact, write_artefact
from ashc_cli.errors import ArtefactError
from ashc_cli.design.pipeline import DESIGN, Folder, needed, run, run_for_verdict, staleness
from ashc_cli.problem.spec import load_spec, parse_spec_text

from .conftest import CUK_PAPER_M


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

    # A changed delta leaves stabilise..inverse alone and reruns delta and bound.
    text = CUK_PAPER_M.read_text().replace('delta: "((xi - 1)**2 + G_L*R_i*xi**2)**2"', 'delta: "1"')
    spec2 = parse_spec_text(text)
    assert staleness(spec2, out, "delta") == "made from another spec (SHA-256 differs)"
    seen.clear()
    arts = run(spec2, out, DESIGN, on_stage=lambda r: seen.append((r.stage, r.status)))
    assert all(status == "ran" for _, status in seen)  # the spec hash is global: every stage reruns
    assert abs(arts["bound"].values["dbar_q0_sampled"] - arts["bound"].values["dbar_q0_identity"]) < 1e-9

    # Rewriting an upstream artefact with other content makes its downstream stale, not its upstream.  (A rerun
    # within the same second writes the same bytes, which rightly leaves the downstream up to date, so the
    # content is changed on purpose here.)
    man = read_artefact(out / "manifold.h5")
    man.meta["note"] = "rewritten by the test"
    prov = man.provenance
    write_artefact(out / "manifold.h5", man, spec_sha256=prov["spec_sha256"], spec_name=prov["spec_name"],
                   parameters=prov["parameters"], upstream=prov["upstream"])
    assert staleness(spec2, out, "stabilise") is None
    assert staleness(spec2, out, "kappa") == "upstream artefact manifold.h5 changed since"
    assert staleness(spec2, out, "bound") == "upstream artefact manifold.h5 changed since"
    assert staleness(spec2, out, "delta") == "upstream artefact manifold.h5 changed since"
    assert staleness(spec2, out, "inverse") == "upstream artefact manifold.h5 changed since"


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
