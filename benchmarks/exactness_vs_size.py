r"""Issue 14 item 5: residuals of conditions a.–d. against the size of the free parameters.

Not a timing: for each model and each parameter block ``Z, Y1, Y2, Y3, J, G`` of a verified
generalized design, add ``size ×`` a perturbation and record the relative residual by the
rule of the one verification routine (`fojax.design.verify`: each condition relative to the
norms of its own terms). Perturbations: all ones, standard normal, and a random *dead*
direction (``Z``: outside the range of $\Pi_Z(I - \Gamma\Gamma^+)$; ``Y_i``: rows in the
range of $\Sigma = [R;\Psi]$; computed here by SVD), scaled to max-entry 1. Sizes 1e0 … 1e13.

Models: the hand example of ``tests/test_parameterization.py`` in generic coordinates (``[R; C]`` of
full row rank), the thesis's example 3.3.7 (Σ rank deficient), the LC filter of
``lc_filter.py`` (``q0 = 3``) and its badly scaled twin.

Measured (``results/exactness_vs_size_latest.json``): the worst over every block,
perturbation and size is 4.7e-16 (hand), 2.0e-15 (3.3.7), 2.1e-16 (LC filter), 5.0e-19
(its twin), against the tolerance 1e-8.

Before the fix (observer_matrices multiplying the dead components into the matrices), the
dead rows gave at 1e8: 4.2e-8 (hand, Z), 6.7e-8 / 6.8e-8 / 1.2e-5 / 3.6e-7 (3.3.7, Z / Y1 /
Y2 / Y3), and at 1e12 2.3e-4 … 1.0e-1.

Run: ``python benchmarks/exactness_vs_size.py`` (about a minute) →
``benchmarks/results/exactness_vs_size_latest.json``.
"""

import json
import os
import pathlib
import sys

import jax


jax.config.update("jax_enable_x64", True)
import numpy as np  # noqa: E402


HERE = pathlib.Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))

from lc_filter import lc_filter  # noqa: E402

import fojax  # noqa: E402
from fojax.design import (  # noqa: E402
    design_functional_observer,
    design_residuals,
    Disk,
    error_dynamics,
    observer_matrices,
    pieces,
    verify,
)
from fojax.design._functional import condition_scales  # noqa: E402  (verify's per-condition scales)


SIZES = [1e0, 1e4, 1e8, 1e10, 1e12, 1e13]


def relative_residual(s, p):
    mats = observer_matrices(s, **{k: np.asarray(v) for k, v in p.items()}, xp=np)
    res = design_residuals(s, mats, xp=np)
    scale = float(res.pop("scale"))
    return verify({k: float(v) for k, v in res.items()}, scale, np.asarray(error_dynamics(mats, xp=np)),
                  Disk(-2.0, 1.0), raise_on_failure=False, scales=condition_scales(s, mats)).relative_residual


def dead_bases(s):
    Psi = np.vstack([np.asarray(s.Eperp) @ np.asarray(s.rules_A())[0], np.asarray(s.C)])
    Gam = np.vstack([np.asarray(s.E), Psi])
    PG = np.eye(Gam.shape[0]) - Gam @ np.linalg.pinv(Gam)
    U, sv, _ = np.linalg.svd(np.asarray(s.PiZ) @ PG)
    Zdead = U[:, int(np.sum(sv > 1e-8)):]
    Sig = np.asarray(pieces(s, xp=np).Sigma)
    U, sv, _ = np.linalg.svd(Sig)
    Ydead = U[:, :int(np.sum(sv > 1e-10 * sv[0]))]
    return {"Z": Zdead, "Y1": Ydead, "Y2": Ydead, "Y3": Ydead}


def table(d):
    s, rng, out = d.structure, np.random.default_rng(0), {}
    bases = dead_bases(s)
    for blk in ["Z", "Y1", "Y2", "Y3", "J", "G"]:
        v0 = np.asarray(d.params[blk])
        if v0.size == 0:
            continue
        for kind in ["ones", "random", "dead"]:
            if kind == "dead" and (blk not in bases or bases[blk].shape[1] == 0):
                continue
            row = []
            for size in SIZES:
                if kind == "ones":
                    dv = np.ones_like(v0)
                elif kind == "random":
                    dv = rng.standard_normal(v0.shape)
                else:
                    dv = rng.standard_normal((v0.shape[0], bases[blk].shape[1])) @ bases[blk].T
                    dv /= np.abs(dv).max()
                row.append(relative_residual(s, dict(d.params, **{blk: v0 + size * dv})))
            out[f"{blk}/{kind}"] = row
    return out


def main():
    A = np.array([[-1.0, 0, 0], [1, -2, 0], [0, 1, -3]])
    B, C, L = np.array([[1.0], [0], [0]]), np.array([[1.0, 0, 0]]), np.array([[0.0, 1, 0]])
    Sx = np.random.default_rng(3).standard_normal((3, 3)) + 3 * np.eye(3)
    hand = fojax.DescriptorSystem(np.eye(3), np.linalg.solve(Sx, A @ Sx), np.linalg.solve(Sx, B), C @ Sx)
    designs = {"hand": design_functional_observer(hand, L @ Sx, kind="generalized", q1=1, region=Disk(-2.0, 1.0),
                                                  R=L @ Sx)}
    ex = fojax.models.example_3_3_7()
    designs["3.3.7"] = design_functional_observer(ex.augmented, ex.L_aug, kind="generalized", region=Disk(-2.0, 1.0))
    for scaled in (False, True):
        m = lc_filter(scaled)
        plant = fojax.DescriptorSystem(m["E"], m["A"], m["B"], m["C"])
        designs["lc_filter_twin" if scaled else "lc_filter"] = design_functional_observer(
            plant, m["L"], kind="generalized", q0=3, q1=1, region=Disk(-2.0, 1.0))
    results = {}
    for name, d in designs.items():
        results[name] = table(d)
        worst = max(max(r) for r in results[name].values())
        print(f"{name}: worst relative residual over all blocks, perturbations and sizes {worst:.1e}")
    out = {"sizes": SIZES, "relative_residual": results, "tolerance": 1e-8,
           "worst": {k: max(max(r) for r in v.values()) for k, v in results.items()},
           "loadavg": os.getloadavg(), "note": "not a timing"}
    path = HERE / "results" / "exactness_vs_size_latest.json"
    path.write_text(json.dumps(out, indent=1))
    print(path)


if __name__ == "__main__":
    main()
