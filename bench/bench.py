"""`make bench`: wall time and peak memory of the design, per stage, on the ladder family and the Cuk spec.

Each measurement runs in a fresh process (`ashc design` on a generated spec), so imports, compilation and
memory are counted as a user sees them; peak memory is the child's maximum resident set size.  Prints one
table (Markdown, ready for README) and the fitted growth exponent of the total time in n (least squares of
log t on log n over the ladder sizes).

    python bench/bench.py [--stages 1 2 4 8 16 32] [--timeout 900]
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from ashc_cli.pipeline import DESIGN

ROOT = Path(__file__).resolve().parents[1]
ASHC = [str(Path(sys.executable).with_name("ashc"))]
STAGES = DESIGN


#: A fresh wrapper per measurement, so RUSAGE_CHILDREN's maximum RSS is that of this one command.
WRAPPER = ("import resource, subprocess, sys; rc = subprocess.run(sys.argv[1:]).returncode; "
           "print('__MAXRSS_KIB__', resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss, file=sys.stderr); sys.exit(rc)")


def run_child(cmd: list[str], timeout: float) -> tuple[float, float, str, int]:
    """Wall seconds, peak RSS (MiB) of the command, its stdout+stderr, its exit code."""
    start = time.perf_counter()
    proc = subprocess.run([sys.executable, "-c", WRAPPER, *cmd], capture_output=True, text=True, timeout=timeout, cwd=ROOT)
    wall = time.perf_counter() - start
    kib = [float(line.split()[1]) for line in proc.stderr.splitlines() if line.startswith("__MAXRSS_KIB__")]
    return wall, (kib[-1] / 1024.0 if kib else float("nan")), proc.stdout + proc.stderr, proc.returncode


def measure(case: str, n: int, cmd: list[str], timeout: float) -> dict:
    """One table row: ``ashc design`` in a fresh process (a timeout gives NaN and exit -1)."""
    try:
        wall, mem, text, rc = run_child(cmd, timeout)
    except subprocess.TimeoutExpired:
        wall, mem, text, rc = float("nan"), float("nan"), "", -1
    return {"case": case, "n": n, "total": wall, "mem": mem, "rc": rc, **parse_progress(text)}


def parse_progress(text: str) -> dict[str, float]:
    times = {}
    for line in text.splitlines():
        parts = line.split()
        if len(parts) > 3 and parts[0] in STAGES and parts[1] == "ran":
            times[parts[0]] = float(parts[2])
    return times


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--stages", type=int, nargs="+", default=[1, 2, 4, 8, 16, 32])
    ap.add_argument("--timeout", type=float, default=900.0)
    args = ap.parse_args()

    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        # Cold start: `ashc --help`, and the bare import time of the dependencies a design needs.
        help_wall, *_ = run_child(ASHC + ["--help"], args.timeout)
        imports = "import numpy, scipy.linalg, scipy.optimize, scipy.integrate, sympy, cvxpy, clarabel, h5py, pydantic, yaml, typer"
        import_wall, _, _, _ = run_child([sys.executable, "-c", imports], args.timeout)
        rows.append(measure("Cuk (n = 4)", 4, ASHC + ["design", "specs/cuk_converter.yaml", "--out", str(tmp / "cuk")], args.timeout))
        cuk_wall = rows[0]["total"]
        for N in args.stages:
            spec = tmp / f"ladder_{N}.yaml"
            subprocess.run(ASHC + ["example", "ladder", "--stages", str(N), "--output", str(spec)], check=True, capture_output=True, cwd=ROOT)
            rows.append(measure(f"ladder N = {N}", 4 * N, ASHC + ["design", str(spec), "--out", str(tmp / f"l{N}")], args.timeout))
            print(f"  measured ladder N = {N} (n = {4 * N}): {rows[-1]['total']:.1f} s", file=sys.stderr, flush=True)

    header = "| case | n | " + " | ".join(STAGES) + " | total (s) | peak RSS (MiB) | exit |"
    print(header)
    print("|" + " --- |" * (len(STAGES) + 5))
    for r in rows:
        cells = " | ".join(f"{r.get(s, float('nan')):.2f}" for s in STAGES)
        print(f"| {r['case']} | {r['n']} | {cells} | {r['total']:.2f} | {r['mem']:.0f} | {r['rc']} |")
    ladder = [r for r in rows if r["case"].startswith("ladder") and r["rc"] == 0 and np.isfinite(r["total"])]
    if len(ladder) >= 2:
        ns = np.log([r["n"] for r in ladder])
        slope = np.polyfit(ns, np.log([r["total"] for r in ladder]), 1)[0]
        # The total includes a fixed start-up (imports); the sum of the stage times shows the growth of the work.
        work = np.polyfit(ns, np.log([sum(r.get(s, 0.0) for s in STAGES) for r in ladder]), 1)[0]
        print(f"\ntotal time grows like n^{slope:.2f}, the sum of the stage times like n^{work:.2f}, "
              f"over n = {ladder[0]['n']}..{ladder[-1]['n']} (least squares on log-log)")
    print(f"cold start: `ashc --help` {help_wall:.2f} s; bare import of the dependencies {import_wall:.2f} s; "
          f"Cuk `ashc design` {cuk_wall:.2f} s = {cuk_wall / import_wall:.1f} x the import time (target <= 2.5 x)")
    (ROOT / "bench" / "last.json").write_text(json.dumps({"rows": rows}) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
