"""Issue 18 target: `fojax study robot_arm_ts` end to end (Monte Carlo + tuning + report) ≤ 3 min.

Runs the public command ``fojax study fojax/examples/robot_arm_ts.toml --out DIR`` in this
process (``fojax.cli._main.main``, what the ``fojax`` entry point calls) after importing
JAX, with ``jax_log_compiles`` on, and records where the time goes:

- wall and CPU time of the whole command (CPU: ``resource.getrusage`` of this process);
- the command's own phases (its "... done in X s" lines: LMI designs, each observer's
  tuning, the Monte Carlo study);
- every XLA compilation JAX logs (function name, seconds), summed per phase and per name,
  so that compile and run can be told apart;
- the trace counts of the tuning step and held-out evaluation (`fojax.tuning._tune.TRACE_COUNTS`)
  and of the study runner (`fojax.studies._runner.TRACE_COUNTS`).

There is no peer: this is a timing target of one command, not a comparison (the study's
numbers are checked by tests/test_cli_ts.py). The machine is shared: the JSON records
``os.getloadavg()`` before and after; say "measured under load" unless both are < 1.

    python benchmarks/study_robot_arm.py            # writes benchmarks/results/study_robot_arm_latest.json
    python benchmarks/study_robot_arm.py --steps 5  # a shorter run while developing (not written)
"""

from __future__ import annotations

import argparse
import collections
import contextlib
import io
import json
import logging
import os
import re
import resource
import sys
import tempfile
import time
from pathlib import Path


HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))
import _common  # noqa: E402


COMPILED = re.compile(r"Finished XLA compilation of (.+?) in ([0-9.eE+-]+) s")


class _Compiles(logging.Handler):
    def __init__(self):
        super().__init__(logging.DEBUG)
        self.events = []  # (monotonic time at the end, name, seconds)

    def emit(self, record):
        m = COMPILED.search(record.getMessage())
        if m:
            self.events.append((time.monotonic(), m.group(1), float(m.group(2))))


class _Tee(io.TextIOBase):
    """stdout copy with the monotonic time of each line (to place compiles in phases)."""

    def __init__(self, out):
        self.out, self.lines, self._buf = out, [], ""

    def write(self, s):
        self.out.write(s)
        self._buf += s
        while "\n" in self._buf:
            line, self._buf = self._buf.split("\n", 1)
            self.lines.append((time.monotonic(), line))
        return len(s)

    def flush(self):
        self.out.flush()


def _cpu() -> float:
    r = resource.getrusage(resource.RUSAGE_SELF)
    return r.ru_utime + r.ru_stime


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--steps", type=int, default=None, help="override [tuning] steps (then nothing is written)")
    ap.add_argument("--out", default=None, help="parent folder of the study's results (default: a temporary one)")
    args = ap.parse_args(argv)

    _common.prefer_checkout()
    # what the `fojax` program does before JAX starts (fojax/cli/_devices.py: XLA:CPU without
    # its fusion emitters); this script runs the command in-process, so it sets them itself
    flags = _common.program_compile_flags()
    load_before = os.getloadavg()
    t0, c0 = time.monotonic(), _cpu()
    import jax

    jax.config.update("jax_log_compiles", True)
    handler = _Compiles()
    logging.getLogger("jax").addHandler(handler)
    logging.getLogger("jax").setLevel(logging.DEBUG)
    from fojax.cli._main import main as fojax_main
    from fojax.studies import _runner
    from fojax.tuning import _tune

    t_import, c_import = time.monotonic() - t0, _cpu() - c0
    cmd = ["study", "robot_arm_ts"]  # a built-in example by name, as `fojax examples` lists it
    if args.steps is not None:
        cmd += ["--steps", str(args.steps)]
    with tempfile.TemporaryDirectory() as tmp:
        cmd += ["--out", args.out or tmp]
        tee = _Tee(sys.stdout)
        t1, c1 = time.monotonic(), _cpu()
        with contextlib.redirect_stdout(tee):
            code = fojax_main(cmd)
        wall, cpu = time.monotonic() - t1, _cpu() - c1
    load_after = os.getloadavg()
    # phases: from each "<what> ..." line to its "done in" line
    phases, start = [], None
    for t, line in tee.lines:
        if line.rstrip().endswith("..."):
            start = (t, line.strip().rstrip(". "))
        m = re.search(r"done in ([0-9.]+) s", line)
        if m and start is not None:
            phases.append({"phase": start[1][:90], "wall_s": float(m.group(1)), "t0": start[0], "t1": t})
            start = None
    for ph in phases:
        ev = [e for e in handler.events if ph["t0"] <= e[0] <= ph["t1"]]
        ph["compiles"] = len(ev)
        ph["compile_wall_s"] = round(sum(e[2] for e in ev), 2)
        del ph["t0"], ph["t1"]
    per_name = collections.defaultdict(lambda: [0, 0.0])
    for _, name, sec in handler.events:
        per_name[name][0] += 1
        per_name[name][1] += sec
    top = sorted(per_name.items(), key=lambda kv: -kv[1][1])[:15]
    result = {
        "machine": _common.machine_info(),
        "xla_flags": os.environ.get("XLA_FLAGS", ""), "program_compile_flag_added": flags,
        "command": "fojax " + " ".join(cmd[:-2] + ["--out", "DIR"]),
        "exit_code": code,
        "import_wall_s": round(t_import, 2), "import_cpu_s": round(c_import, 2),
        "command_wall_s": round(wall, 2), "command_cpu_s": round(cpu, 2),
        "total_wall_s": round(t_import + wall, 2), "total_cpu_s": round(c_import + cpu, 2),
        "phases": phases,
        "compiles_total": len(handler.events),
        "compile_wall_s_total": round(sum(e[2] for e in handler.events), 2),
        "compiles_by_name": [{"name": n, "count": c, "wall_s": round(s, 2)} for n, (c, s) in top],
        "trace_counts": {"tune": dict(_tune.TRACE_COUNTS), "run_study": dict(_runner.TRACE_COUNTS)},
        "loadavg_before": load_before, "loadavg_after": load_after,
        "note": "measured under load (shared 2-core machine)" if max(load_before[0], load_after[0]) >= 1 else "quiet",
    }
    print(json.dumps(result, indent=1))
    if args.steps is None:
        _common.write_result(HERE / "results" / "study_robot_arm_latest.json", result)
    return code


if __name__ == "__main__":
    raise SystemExit(main())
