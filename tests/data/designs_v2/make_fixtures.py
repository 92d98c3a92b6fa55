"""Wrote these v2 design files (format_version 2) with fojax at commit 964645a, before the generic
format 3 of AbstractDesign.save. Kept as written: they test that old files still load. Do not
re-run (needs that commit)."""
import pathlib
import subprocess

import jax
import numpy as np

import fojax
from fojax.design import (
    design_fault_estimator,
    design_finite_time_observer,
    design_functional_observer,
    design_ts_observer,
    design_unknown_input_observer,
    Disk,
)
from fojax.results import save_design


jax.config.update("jax_enable_x64", True)
out = pathlib.Path("tests/data/designs_v2")
ex413 = fojax.models.example_4_1_3()
E, A, B, C, L = (np.asarray(x) for x in (ex413.E, ex413.A, ex413.B, ex413.C, ex413.L))
closed = fojax.DescriptorSystem(E, A + B @ L, B, C)
ex312 = fojax.models.example_3_1_2()
ex337 = fojax.models.example_3_3_7()
sys337 = fojax.DescriptorSystem(ex337.E, ex337.A, ex337.B, ex337.C)
arm = fojax.models.robot_arm_ts().system
designs = {
    "functional": design_functional_observer(closed, L, kind="generalized", region=Disk(-2.0, 1.0)),
    "hinf": design_functional_observer(ex413.system, ex413.L, region=Disk(-2.0, 1.0), objective="hinf",
                                       Bw=0.5 * np.eye(4), Dv=0.1 * np.eye(3)),
    "ts": design_ts_observer(arm, np.eye(5)[[1, 3]], kind="generalized"),
    "uio": design_unknown_input_observer(closed, np.eye(4)[:, [2]], L),
    "finite_time": design_finite_time_observer(ex312.system, ex312.L, h=0.5, regions=((-5, 0.5), (-2, 0.5))),
    "fault": design_fault_estimator(sys337, ex337.L, Fa=ex337.Fa, Fs=ex337.Fs, kind="generalized",
                                    region=Disk(-2.0, 1.0)),
}
commit = subprocess.check_output(["git", "rev-parse", "HEAD"]).decode().strip()
for k, d in designs.items():
    p = save_design(d, out / f"{k}.npz", metadata={"case": k, "written_by_commit": commit})
    print(k, p.stat().st_size, d.report.passed if hasattr(d, "report") else "")
