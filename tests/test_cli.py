"""Tests of the command line through the real `ashc` entry point (the contract of cli.md)."""

import json
import os
import re
import shutil
import subprocess
import sys
import threading
from pathlib import Path

import pytest
import typer
from typer.testing import CliRunner

from ashc_cli.design.artefacts import read_artefact
from ashc_cli.cli import Progress, app, plain_text

from .conftest import CUK, CUK_PAPER_M, ROOT, ashc, edited

SUMMARY_KEYS = {
    "stabilise": ["lambda", "M", "lmi_margin"],
    "manifold": ["p", "residual"],
    "kappa": ["kappa"],
    "inverse": ["V", "m", "left_inverse_residual", "condition_ii"],
    "delta": ["delta", "b", "c", "min_singular_value"],
    "bound": ["alpha_h", "epsilon", "dbar_q0", "dbar_ls", "gain"],
}


def test_design_progress_lines(cli_run):
    # Progress (the stage lines) goes to stderr; stdout carries only the result, the design's summary line.
    err = cli_run["design"].stderr.splitlines()
    stages = [line.split()[0] for line in err[:6]]
    assert stages == list(SUMMARY_KEYS)
    assert all(" s  " in line for line in err[:6])
    out = cli_run["design"].stdout.splitlines()
    assert len(out) == 1 and ": proved (15/15 conditions of Problem 1); |psi - y| <= 23.836 ||v||_inf" in out[0]


def test_design_skips_up_to_date_stages(cli_run):
    again = ashc("design", str(CUK), "--out", str(cli_run["out"]), check=True)
    assert all("up to date" in line for line in again.stderr.splitlines()[:6])


def test_summary_json_keys(cli_run):
    data = json.loads(ashc("summary", str(cli_run["out"]), "--json", check=True).stdout)
    for stage, keys in SUMMARY_KEYS.items():
        for key in keys:
            assert key in data[stage], f"{stage}.{key}"
    assert data["stabilise"]["lmi_margin"] <= 0
    assert data["stabilise"]["lambda"] == 2.0
    tr = data["simulate"]["tracking"]
    for key in ("max_abs_error", "v_inf", "u_min", "u_max"):
        assert key in tr
    assert data["simulate"]["m_relation"]["max_abs_error"] < 1e-6


@pytest.mark.slow
def test_eval_prints_the_contract_shape(cli_run):
    out = ashc("eval", str(cli_run["out"]), "p", "--at", "xi=0.6156", check=True).stdout.strip()
    assert out.startswith("p(xi=0.6156) = [1.3678")
    out = ashc("eval", str(cli_run["out"]), "m", "--at", "x1=10.3256,x2=2.0561,x3=-4.9785,x4=-6.9732", check=True).stdout.strip()
    assert out.startswith("m(") and out.endswith("]") and "0.3677" in out
    out = ashc("eval", str(cli_run["out"]), "kappa", "--at", "xi=0", check=True).stdout.strip()
    assert out == "kappa(xi=0) = [0]"
    data = json.loads(ashc("eval", str(cli_run["out"]), "c", "--at", "x1=1,x2=2,x3=3,x4=-4", "--json", check=True).stdout)
    assert data["value"] == [0.0]
    theta = ashc("eval", str(cli_run["out"]), "theta", "--at", "xi=0.5,x1=1,x2=2,x3=3,x4=-4", check=True).stdout
    assert theta.startswith("theta(") and theta.count(",") >= 3


@pytest.mark.parametrize(
    "args, code, fragment",
    [
        (["design", "no/such.yaml"], 2, "error: no/such.yaml: no such file"),
        (["eval", "/nonexistent", "p", "--at", "xi=1"], 5, "holds no ashc artefact"),
    ],
)
def test_errors_are_one_line_with_code(args, code, fragment):
    proc = ashc(*args)
    assert proc.returncode == code
    assert proc.stderr.count("\n") == 1 and fragment in proc.stderr
    assert "Traceback" not in proc.stderr


def test_bad_spec_one_line_and_debug_traceback(tmp_path):
    spec = tmp_path / "bad.yaml"
    spec.write_text(CUK.read_text().replace('"x1/C_2"', "\"__import__('os').system('touch pwned')\""))
    proc = ashc("design", str(spec), "--out", str(tmp_path / "o"))
    assert proc.returncode == 2
    assert proc.stderr.startswith("error: concrete.f_bar[1]: call of '__import__") and "is not allowed" in proc.stderr
    assert "Traceback" not in proc.stderr and not (tmp_path / "o").exists()
    debug = ashc("--debug", "design", str(spec), "--out", str(tmp_path / "o"))
    assert debug.returncode == 2 and "Traceback" in debug.stderr


def test_design_condition_exit_3(tmp_path):
    spec = tmp_path / "short_V.yaml"
    spec.write_text(CUK_PAPER_M.read_text().replace("domain: [[0, 0.95]]", "domain: [[0, 0.9]]"))
    proc = ashc("design", str(spec), "--out", str(tmp_path / "o"))
    assert proc.returncode == 3 and "(eq. (10))" in proc.stderr   # eq. SimuLocalRequire, as the paper numbers it
    # The stages before the failing one were written and stay valid.
    assert (tmp_path / "o" / "kappa.h5").exists() and not (tmp_path / "o" / "inverse.h5").exists()


def test_help_explains():
    proc = ashc("--help", check=True)
    for word in ("design", "simulate", "summary", "eval", "Exit codes"):
        assert word in proc.stdout
    assert "eq. (28)" in ashc("stabilise", "--help", check=True).stdout


# --- issue 14: one output channel, progress, options that do what they say ------------------------------

#: One progress line: `<stage> <status> <seconds> s  <headline>`.
STAGE_LINE = re.compile(r"^({}) +(ran|up to date) +\d+\.\d\d s  \S".format("|".join([*SUMMARY_KEYS, "simulate", "falsify"])))
#: A negative zero standing alone ("-0", "-0.0"; not "-0.5").
NEGATIVE_ZERO = re.compile(r"(?<![\w.])-0(?:\.0*)?(?:e[+-]?0+)?(?![\w.])")


def _copy(cli_run, tmp_path: Path) -> Path:
    """A copy of the session's designed (and simulated) Cuk folder that a test may change."""
    out = tmp_path / "out"
    shutil.copytree(cli_run["out"], out)
    return out


def invoke(*args):
    """The typer app in-process (stderr is not a terminal), for options that fail or finish fast."""
    return CliRunner().invoke(app, [str(a) for a in args])


def test_stdout_carries_only_the_result(cli_run):
    # simulate used to print its stage lines on stdout; now stdout is the artefact's path, the stage lines are stderr.
    sim = cli_run["simulate"]
    assert sim.stdout == f"{cli_run['out'] / 'simulate.h5'}\n"
    lines = sim.stderr.splitlines()
    assert [line.split()[0] for line in lines] == [*SUMMARY_KEYS, "simulate"]
    assert all(STAGE_LINE.match(line) for line in lines), lines


@pytest.mark.slow
def test_falsify_then_report_reruns_only_when_the_options_differ(cli_run, tmp_path):
    out = _copy(cli_run, tmp_path)
    falsify = ashc("falsify", str(CUK), "--out", str(out), "--runs", "8", "--t-final", "2", check=True)
    # Not a terminal: the stage lines only (the progress bar's label used to be printed among them).
    assert falsify.stdout.startswith("falsify 'cuk_converter': 8 runs") and falsify.stdout.count("\n") == 1
    lines = falsify.stderr.splitlines()
    assert [line.split()[0] for line in lines] == [*SUMMARY_KEYS, "falsify"]
    assert all(STAGE_LINE.match(line) for line in lines), lines

    # The same settings: the stored falsify.h5 is used.
    same = ashc("report", str(CUK), "--out", str(out), "--runs", "8", "--t-final", "2", check=True)
    assert any(line.startswith("falsify    up to date") for line in same.stderr.splitlines()), same.stderr
    assert "running falsify" not in same.stderr and same.stdout.startswith(str(out / "report.html"))
    # Other settings: never silently reused; --frozen refuses, naming the difference.
    frozen = ashc("report", str(CUK), "--out", str(out), "--runs", "9", "--t-final", "2", "--frozen")
    assert frozen.returncode == 5
    assert frozen.stderr.splitlines()[-1] == ("error: falsify.h5: was made with --runs 8, not 9 (--frozen runs nothing); "
                                              "expected `ashc falsify SPEC --runs 9 --seed 0 --t-final 2` first, or drop --frozen")
    again = ashc("report", str(CUK), "--out", str(out), "--runs", "9", "--t-final", "2", check=True)
    assert "note: running falsify --runs 9 --seed 0 --t-final 2: falsify.h5 was made with --runs 8, not 9" in again.stderr
    assert any(line.startswith("falsify    ran") for line in again.stderr.splitlines())
    stored = read_artefact(out / "falsify.h5")
    assert stored.meta["runs"] == 9 and stored.meta["seed"] == 0 and stored.values["t_final"] == 2.0
    # A setting not given keeps the stored run's (9 runs), the one given (--seed 1) reruns it.
    seed = ashc("report", str(CUK), "--out", str(out), "--seed", "1", check=True)
    assert "note: running falsify --runs 9 --seed 1 --t-final 2: falsify.h5 was made with --seed 0, not 1" in seed.stderr


def _with_terminal_stderr(*args: str) -> tuple[subprocess.CompletedProcess, str]:
    """Run ashc with stderr on a pseudo-terminal (stdout a pipe); return the process and what stderr showed."""
    pty = pytest.importorskip("pty")
    master, slave = pty.openpty()
    exe = Path(sys.executable).with_name("ashc")
    proc = subprocess.Popen([str(exe), *args], stdout=subprocess.PIPE, stderr=slave, cwd=ROOT, text=True,
                            env={**os.environ, "TERM": "xterm", "COLUMNS": "120", "PYTHONWARNINGS": "ignore"})
    os.close(slave)
    chunks: list[bytes] = []

    def read() -> None:
        while True:
            try:
                data = os.read(master, 4096)
            except OSError:  # the terminal closed (EIO on Linux)
                return
            if not data:
                return
            chunks.append(data)

    reader = threading.Thread(target=read)
    reader.start()
    stdout = proc.stdout.read()
    proc.wait(timeout=600)
    reader.join(timeout=10)
    os.close(master)
    return subprocess.CompletedProcess(proc.args, proc.returncode, stdout, None), b"".join(chunks).decode(errors="replace")


def test_live_progress_when_stderr_is_a_terminal(cli_run, tmp_path):
    out = _copy(cli_run, tmp_path)
    proc, shown = _with_terminal_stderr("falsify", str(CUK), "--out", str(out), "--runs", "8", "--t-final", "2")
    assert proc.returncode == 0, shown
    # The bar (with runs/s) is on the terminal, and the stage lines; stdout is the result line alone, no escapes.
    assert "falsify: 8 runs" in shown and "runs/s" in shown and "\x1b[" in shown
    plain = re.sub(r"\x1b\[[0-9;?]*[A-Za-z]", "", shown).replace("\r", "\n")
    assert [line.split()[0] for line in plain.splitlines() if STAGE_LINE.match(line)] == [*SUMMARY_KEYS, "falsify"], plain
    assert proc.stdout.startswith("falsify 'cuk_converter': 8 runs") and proc.stdout.count("\n") == 1 and "\x1b" not in proc.stdout


def test_progress_without_a_terminal_prints_lines_only(capsys):
    progress = Progress(live=False)
    progress.start("simulate: forced")
    progress.update(completed=3, note="10 runs/s")
    progress.line("kappa      ran           0.06 s  kappa(V) = [[-126.1875, -0.0]]")
    progress.stop()
    captured = capsys.readouterr()
    assert captured.out == "" and captured.err == "kappa      ran           0.06 s  kappa(V) = [[-126.1875, 0.0]]\n"


def test_frozen_on_every_command_that_runs_stages(cli_run, tmp_path):
    out = _copy(cli_run, tmp_path)
    ok = invoke("design", CUK, "--out", out, "--frozen")
    assert ok.exit_code == 0 and "proved (15/15 conditions of Problem 1)" in ok.stdout
    assert all("up to date" in line for line in ok.stderr.splitlines())
    (out / "delta.h5").unlink()
    for command in ("design", "check", "plot", "falsify", "report", "simulate", "bound"):
        res = invoke(command, CUK, "--out", out, "--frozen")
        assert res.exit_code == 5, (command, res.stderr)
        assert res.stderr.splitlines()[-1] == ("error: delta.h5: is not up to date (no artefact yet); "
                                               "expected run `ashc design SPEC` first, or drop --frozen"), command
    assert not (out / "delta.h5").exists()  # nothing was recomputed
    assert invoke("kappa", CUK, "--out", out, "--frozen").exit_code == 0  # kappa does not need delta


def test_force_with_frozen(cli_run, tmp_path):
    out = _copy(cli_run, tmp_path)
    for command in ("design", "check", "plot", "report"):
        res = invoke(command, CUK, "--out", out, "--force", "--frozen")
        assert res.exit_code == 2, (command, res.stderr)
        assert res.stderr.startswith(f"error: --force: cannot be combined with --frozen on `ashc {command}`") and res.stderr.count("\n") == 1
    # A stage command: --force --frozen recomputes that stage only (it used to fail on the "forced" upstream).
    res = invoke("kappa", CUK, "--out", out, "--force", "--frozen")
    assert res.exit_code == 0, res.stderr
    assert [line.split()[:2] for line in res.stderr.splitlines()] == [["manifold", "up"], ["kappa", "ran"]]
    assert res.stdout == f"{out / 'kappa.h5'}\n"


def test_numeric_on_up_to_date_stages_is_not_silent(cli_run, tmp_path):
    out = _copy(cli_run, tmp_path)
    res = invoke("kappa", CUK, "--out", out, "--numeric")
    assert res.exit_code == 0
    assert res.stderr.splitlines()[-1] == ("note: --numeric did not apply to the stage(s) kept as they were (manifold, kappa); "
                                           "add --force to recompute them")


def test_sweep_refuses_workers_with_a_scheduler():
    res = invoke("sweep", CUK, "--param", "E=10:12:2", "--scheduler", "tcp://127.0.0.1:9", "--workers", "3")
    assert res.exit_code == 2
    assert res.stderr == ("error: --workers: 3 worker processes are for the local cluster, but --scheduler tcp://127.0.0.1:9 is given; "
                          "expected --workers (a local cluster) or --scheduler (a running one), not both\n")


def test_help_summaries_are_whole_sentences():
    # click cut the summaries at the first ". ": "Compose the abstract output map kappa = h o p (eq."
    text = ashc("--help", check=True).stdout
    listing = text.split("Commands:\n", 1)[1].splitlines()
    group = typer.main.get_command(app)
    assert len(listing) == len(group.commands)  # one line each: nothing wrapped
    for line in listing:
        name, summary_text = line.split(None, 1)
        assert name in group.commands
        assert summary_text.endswith(".") and not summary_text.endswith("...") and "eq." not in summary_text, line


def test_debug_is_no_option_and_works_anywhere(tmp_path):
    group = typer.main.get_command(app)
    for name, command in group.commands.items():
        assert "--debug" not in command.get_help(typer.Context(command, info_name=name)), name
    # After the command and given twice (the second one used to reach click: "No such option").
    proc = ashc("--debug", "design", "no/such.yaml", "--debug")
    assert proc.returncode == 2 and "Traceback" in proc.stderr and "No such option" not in proc.stderr


def test_negative_zero_prints_as_zero(cli_run):
    out = cli_run["out"]
    assert ashc("eval", str(out), "kappa", "--at", "xi=-0", check=True).stdout == "kappa(xi=0) = [0]\n"
    text = ashc("summary", str(out), check=True).stdout
    assert "range_on_V = [[-126.19, 0]]" in text and not NEGATIVE_ZERO.search(text)   # 5 significant digits for people
    data = ashc("summary", str(out), "--json", check=True).stdout
    assert not re.search(r"-0\.0(?!\d)", data)
    kappa_line = next(line for line in cli_run["design"].stderr.splitlines() if line.startswith("kappa"))
    assert kappa_line.endswith("kappa(V) = [[-126.1875, 0.0]]")
    assert not NEGATIVE_ZERO.search(cli_run["design"].stdout + cli_run["design"].stderr)


@pytest.mark.parametrize("text, shown", [
    ("kappa(V) = [[-126.1875, -0.0]]", "kappa(V) = [[-126.1875, 0.0]]"),
    ("[-0, 1, -0.5, -0.05, x-0, 1e-0, -0e+00]", "[0, 1, -0.5, -0.05, x-0, 1e-0, 0e+00]"),
    ("lmi_margin = -0.0317", "lmi_margin = -0.0317"),
])
def test_plain_text_drops_the_sign_of_zero_only(text, shown):
    assert plain_text(text) == shown


@pytest.mark.parametrize("command", ["falsify", "report"])
def test_t_final_must_be_positive_before_any_work(command, tmp_path):
    # --t-final 0 used to design first and then fail as a design condition (exit 3).
    res = invoke(command, CUK, "--out", tmp_path / "o", "--t-final", "0")
    assert res.exit_code == 2
    assert res.stderr == "error: --t-final: 0 s; expected a positive, finite length of run in seconds\n"
    assert not (tmp_path / "o").exists()


def test_a_reader_that_goes_away_is_no_internal_error(tmp_path):
    # `ashc summary out | head -1`: the pipe closes before summary is done; exit 0, no "error: internal".
    import subprocess

    from .conftest import SPECS, ashc

    ashc("design", str(SPECS / "cuk_converter.yaml"), "--out", str(tmp_path), check=True)
    proc = subprocess.run(f"{sys.executable} -m ashc_cli.cli summary {tmp_path} | head -c 10", shell=True, capture_output=True, text=True, timeout=120)
    assert "internal" not in proc.stderr and "Traceback" not in proc.stderr


def test_bare_ashc_prints_the_help_and_version_flags_print_the_version():
    from ashc_cli import __version__

    bare = ashc()
    assert bare.returncode == 0 and bare.stdout.startswith("Usage: ashc") and "Commands:" in bare.stdout
    for flag in ("--version", "-V"):
        proc = ashc(flag)
        assert proc.returncode == 0 and proc.stdout == f"ashc {__version__}\n"
    assert "--install-completion" in ashc("--help").stdout    # typer's shell completion


def test_ctrl_c_while_the_libraries_load_is_one_line_and_exit_130(tmp_path):
    import signal
    import time

    from .conftest import SPECS

    exe = Path(sys.executable).with_name("ashc")
    cmd = [str(exe)] if exe.exists() else [sys.executable, "-m", "ashc_cli"]
    # Once numpy's extension is mapped into the process (/proc/PID/maps), the console script is inside main(),
    # importing the command line, and the import of sympy, scipy, cvxpy and the stages is still ahead.  A fixed 0.1 s
    # sleep failed on a loaded machine: the signal came before the interpreter had started, and killed it.  The
    # command is a design (seconds of imports and work after numpy), not `summary` of a missing folder: on a fresh
    # clone under `make test` that one ended by itself (exit 5) before this loop was scheduled to send the signal, in
    # 5 tries of 5.  A Ctrl-C during the design's work must read the same.
    for _ in range(3):
        # SIGINT at its default in the child whatever the runner's disposition (a background job inherits it ignored)
        proc = subprocess.Popen(cmd + ["design", str(SPECS / "cuk_converter.yaml"), "--out", str(tmp_path / "out")],
                                stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                                preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL))
        maps = Path(f"/proc/{proc.pid}/maps")
        deadline = time.monotonic() + 60
        try:
            while time.monotonic() < deadline and proc.poll() is None and "_multiarray_umath" not in maps.read_text():
                time.sleep(0.002)
        except FileNotFoundError:       # the process ended between the poll and the read
            pass
        if proc.poll() is None:
            proc.send_signal(signal.SIGINT)
            out, err = proc.communicate(timeout=120)
            break
        proc.communicate()
    else:
        pytest.fail("the design ended before the signal in 3 tries: no Ctrl-C was tested")
    assert proc.returncode == 130, (proc.returncode, err[-2000:])
    assert err == "error: interrupted; artefacts written before the interruption are intact\n"
    assert "Traceback" not in out


# --- the first hour: a quick command line, counts that agree, stale scenarios named, evidence kept ---------


def test_the_command_line_loads_no_design_machinery_until_a_command_needs_it():
    """`ashc --help`, `--version` and an error in the arguments must return at once: importing the command line
    pulls in typer and numpy, never sympy, scipy, cvxpy, numba, h5py or matplotlib (about a second, 200 MB)."""
    code = ("import sys, ashc_cli.cli; "
            "print(sorted(m for m in ('sympy', 'scipy', 'cvxpy', 'numba', 'h5py', 'matplotlib', 'pydantic') if m in sys.modules))")
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert proc.stdout.strip() == "[]", proc.stdout


def test_the_light_names_of_the_command_line_are_the_pipelines():
    from ashc_cli.cli import common
    from ashc_cli.design.pipeline import STAGES
    from ashc_cli.outputs.query import EVALUABLE
    from ashc_cli.products import falsify

    assert list(common.STAGE_HELP) == list(STAGES)
    assert common.EVALUABLE_NAMES == tuple(EVALUABLE)
    assert common.FALSIFY == falsify.NAME


def test_check_names_a_simulate_artefact_of_an_earlier_design_stale(tmp_path):
    out = tmp_path / "cuk"
    ashc("design", str(CUK), "--out", str(out), check=True)
    ashc("simulate", str(CUK), "--out", str(out), check=True)
    lines = ashc("check", str(CUK), "--out", str(out), check=True).stdout.splitlines()
    rows = [line for line in lines if line.startswith("  pass ")]
    assert len(rows) == 15                                       # the 15 conditions of Problem 1, as design counts them
    assert lines[-2] == (f"Simulated scenarios (`ashc simulate`; not part of the verdict): 6 of 6 checks pass "
                         f"(`ashc summary {out}` lists them)")
    ashc("bound", str(CUK), "--out", str(out), "--force", check=True)   # a new bound.h5: the runs were for the old one
    lines = ashc("check", str(CUK), "--out", str(out), check=True).stdout.splitlines()
    assert lines[-2] == (f"Simulated scenarios: {out / 'simulate.h5'} is stale, made for an earlier design (bound.h5 "
                         f"changed since); not shown. Rerun `ashc simulate SPEC --out {out}`")
    got = json.loads(ashc("check", str(CUK), "--out", str(out), "--json", check=True).stdout)
    assert got["simulated"] == [] and got["simulated_stale"] == "made for an earlier design (bound.h5 changed since)"


def test_report_keeps_a_larger_falsification_than_it_asks_for(tmp_path):
    out = tmp_path / "cuk"
    ashc("falsify", str(CUK), "--out", str(out), "--runs", "40", "--t-final", "2", check=True)
    rep = ashc("report", str(CUK), "--out", str(out), "--runs", "8", "--t-final", "2", check=True)
    assert "note: falsify.h5 kept: its 40 runs (seed 0, t_final 2 s) are more evidence than --runs 8" in rep.stderr
    assert not any(line.startswith("falsify    ran") for line in rep.stderr.splitlines())
    page = (out / "report.html").read_text(encoding="utf-8")
    assert "40 searched closed-loop runs in all" in page
    # the headline leads with the runs started on the manifold, where the ratio tests G
    first = ashc("falsify", str(CUK), "--out", str(out), "--runs", "40", "--t-final", "2", check=True).stdout.splitlines()[0]
    assert first.startswith("falsify 'cuk_converter': 40 runs; started on the manifold (W0 = 0, where only G ||v||_inf counts): "
                            "largest |psi - y| / bound = "), first


def test_an_unknown_name_in_f_bar_is_offered_only_the_names_f_bar_may_use(tmp_path):
    bad = edited(CUK, tmp_path, ('"x1/C_2"', '"x1/C_2 + x9"'))
    err = ashc("check", str(bad), "--out", str(tmp_path / "o")).stderr.strip().splitlines()[-1]
    assert err.startswith("error: concrete.f_bar[1]: unknown name 'x9'"), err
    offered = err.split("declared names (")[1].split(")")[0].split(", ")
    assert "x4" in offered and "E" in offered and not {"u", "v", "xi"} & set(offered), offered


def test_a_usage_error_is_one_line_with_the_option_the_value_and_what_was_expected():
    cases = {("falsify", str(CUK), "--runs", "0"): "error: --runs: '0'; expected a number >= 1 (see `ashc falsify --help`)",
             ("falsify", str(CUK), "--runs", "abc"): "error: --runs: 'abc'; expected a whole number (see `ashc falsify --help`)",
             ("plot", str(CUK), "--format", "jpg"): "error: --format: 'jpg'; expected one of 'png', 'pdf', 'svg' (see `ashc plot --help`)",
             ("design",): "error: Missing argument 'SPEC' (see `ashc design --help`)"}
    for args, line in cases.items():
        proc = ashc(*args)
        assert proc.returncode == 2 and proc.stderr == line + "\n", (args, proc.stderr)


def test_example_does_not_overwrite_a_file_without_force(tmp_path):
    mine = tmp_path / "mine.yaml"
    mine.write_text("# my edits\n", encoding="utf-8")
    proc = ashc("example", "cuk", "--output", str(mine))
    assert proc.returncode == 2 and proc.stderr.strip() == f"error: --output: {mine} exists; expected a new file, or --force to overwrite it"
    assert mine.read_text(encoding="utf-8") == "# my edits\n"
    ashc("example", "cuk", "--output", str(mine), "--force", check=True)
    assert mine.read_text(encoding="utf-8").startswith("# DC-to-DC Cuk converter")


@pytest.mark.parametrize("where", ["file/out", "/dev/null/out", "/proc/ashc_no/out"])
def test_an_out_that_cannot_be_a_folder_is_refused_before_anything_is_computed(tmp_path, where):
    # It used to exit 1 "internal: NotADirectoryError" after the stabilise stage had computed (issue 39).
    (tmp_path / "file").write_text("")
    out = tmp_path / where if where.startswith("file") else Path(where)
    proc = ashc("design", str(CUK), "--out", str(out))
    assert proc.returncode == 2, proc.stderr
    lines = proc.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith(f"error: --out: '{out}' ")
    assert "expected a folder that exists or can be created" in lines[0]
    assert "stabilise" not in proc.stderr and not out.exists()


def test_a_missing_out_folder_is_probed_without_leaving_a_trace(tmp_path):
    from ashc_cli.cli.common import usable_folder

    usable_folder(tmp_path / "a" / "b" / "c", "--out")
    assert list(tmp_path.iterdir()) == []
