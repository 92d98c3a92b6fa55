"""Issue 13 (`fojax study` ≤ 30 s): where the time of the README's first command goes.

Runs ``fojax study --out <tmp>`` (the default example, §3.3.7) in this process through the
public CLI entry point (`fojax.cli.main`), after the imports (install and import time
excluded, as in the issue's target), and records:

- the total wall and process CPU seconds of the command;
- each phase the command reports (``<message> ...`` then ``done in X s``: designs,
  tuning, Monte Carlo study, report/figures), parsed from its own output;
- the command's closing lines on the tuning (study IAE total and sum of mean peaks, LMI
  design -> tuned, on the study's samples) as ``tuning_result``;
- the trace counts of the compiled study / tuning functions after the run
  (`fojax.tuning._tune.TRACE_COUNTS`, the study engines' counters), which show whether a phase
  compiled its function again;
- ``os.getloadavg()`` before and after: the reference machine is a shared 2-core box, so
  the numbers are measured under load unless the load average is below 1.

One JAX device, as ``fojax study`` by default; ``--host-devices N`` gives JAX N host devices
before it starts, as ``fojax study --devices N`` does (`fojax.cli._devices`); XLA's compile
flag as the program sets it (`fojax.cli._devices.configure_compiler`; recorded as ``xla_flags``).

    python benchmarks/cli_study.py            # writes benchmarks/results/cli_study_latest.json
"""

from __future__ import annotations

import argparse
import contextlib
import io
import os
import re
import sys
import tempfile
import time
from pathlib import Path


HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))
import _common  # noqa: E402


_common.limit_blas_threads()
_common.prefer_checkout()
# `fojax study --devices N` (fojax.cli._devices): --host-devices N JAX host devices, set before
# JAX is imported; without it one device, as `fojax study` by default
if any(a.startswith("--host-devices") for a in sys.argv[1:]):
    _common.force_host_devices()
# and its compile flag (fojax.cli._devices.configure_compiler): what the program runs with
_common.program_compile_flags()

import jax  # noqa: E402

import fojax  # noqa: E402
import fojax.cli  # noqa: E402
from fojax.studies import _exact, _runner  # noqa: E402
from fojax.tuning import _tune  # noqa: E402


class _Tee(io.TextIOBase):
    def __init__(self, *streams):
        self.streams = streams

    def write(self, s):
        for st in self.streams:
            st.write(s)
        return len(s)

    def flush(self):
        for st in self.streams:
            st.flush()


def phases(text: str) -> list[dict]:
    """``[{phase, s}]``: every ``<message> ...`` line followed (later) by ``done in X s``."""
    out, open_ = [], []
    for line in text.splitlines():
        line = line.split("\r")[-1]
        m = re.match(r"^\s*done in ([0-9.]+) s", line)
        if m and open_:
            out.append(dict(phase=open_.pop(), s=float(m.group(1))))
        elif line.rstrip().endswith("...") and not line.startswith(" "):
            open_.append(line.rstrip()[:-3].strip())
    return out


# The issues' wall-clock targets for the command (install and import excluded).
TARGETS = {None: "fojax study <= 30 s (issue 13)", "robot_arm_ts": "fojax study robot_arm_ts <= 3 min (issue 18)"}


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--example", default=None, help="a config or shipped example (default: the command's own)")
    ap.add_argument("--out", default=str(_common.RESULTS / "cli_study_latest.json"))
    ap.add_argument("--host-devices", type=int, default=None,
                    help="JAX host devices (default 1, as `fojax study`; read before JAX starts)")
    args = ap.parse_args()
    info = _common.machine_info()
    load0 = _common.load_average()
    buf = io.StringIO()
    with tempfile.TemporaryDirectory() as tmp:
        w, c = time.perf_counter(), time.process_time()
        with contextlib.redirect_stdout(_Tee(sys.stdout, buf)), contextlib.redirect_stderr(_Tee(sys.stderr, buf)):
            rc = fojax.cli.main(["study"] + ([args.example] if args.example else []) + ["--out", tmp])
        wall, cpu = time.perf_counter() - w, time.process_time() - c
    traces = {f"tuning.{k}": v for k, v in _tune.TRACE_COUNTS.items()}
    traces.update({f"studies.{k}": v for k, v in _runner.TRACE_COUNTS.items()})
    traces.update({f"studies._exact.{k}": v for k, v in _exact.TRACE_COUNTS.items()})
    result = dict(
        status="complete" if rc == 0 else f"failed (exit {rc})",
        benchmark=(
            "cli_study (issue 13): `fojax study` on the default example, install/import excluded"
            if args.example is None
            else f"cli_study (issue 18): `fojax study {args.example}`, install/import excluded"
        ),
        target=TARGETS.get(args.example, "none stated"),
        command=f"fojax study {args.example or ''} --out <tmp>".replace("  ", " "),
        wall_s=wall, cpu_s=cpu, phases=phases(buf.getvalue()), trace_counts=traces,
        # the command's own summary of what the tuning changed on the study's samples
        tuning_result=[line.strip() for line in buf.getvalue().splitlines()
                       if line.startswith("tuning '") and "study IAE total" in line],
        jax_devices=jax.device_count(), xla_flags=os.environ.get("XLA_FLAGS", ""),
        machine=info, load_average_before=load0, load_average_after=_common.load_average(),
        note="measured once; on a shared 2-core machine under load unless the load averages are < 1",
    )
    if args.example is not None and args.out == ap.get_default("out"):
        args.out = str(_common.RESULTS / f"cli_study_{Path(args.example).stem}_latest.json")
    _common.write_result(args.out, result)
    print(f"wall {wall:.1f} s, cpu {cpu:.1f} s, phases {result['phases']}, traces {traces}", flush=True)


if __name__ == "__main__":
    main()
