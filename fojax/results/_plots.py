"""Figures for papers: poles with the design region, estimates with Monte Carlo bands,
error distributions per observer, and the tuning curve.

Every function renders with Matplotlib's Agg canvas (no display, no global `pyplot`
state), writes a PNG of exactly ``size`` pixels (default 800x600) atomically, and
returns its path. An existing file is never replaced unless ``overwrite=True``.
"""

from __future__ import annotations

import io
import pathlib
from collections.abc import Mapping, Sequence

import numpy as np

from ._io import atomic_write_bytes


DEFAULT_SIZE = (800, 600)
_DPI = 100


def _figure(size):
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    w, h = size
    fig = Figure(figsize=(w / _DPI, h / _DPI), dpi=_DPI)
    FigureCanvasAgg(fig)
    return fig


def _save(fig, path, overwrite: bool) -> pathlib.Path:
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=_DPI)  # no bbox_inches: keeps the pixel size exact
    return atomic_write_bytes(path, buf.getvalue(), overwrite=overwrite)


def _as_2d(name, a, T=None):
    a = np.asarray(a, dtype=float)
    if a.ndim == 1:
        a = a[:, None]
    if a.ndim != 2 or (T is not None and a.shape[0] != T):
        raise ValueError(f"{name} must have shape (len(ts), q) or (len(ts),); got {a.shape}")
    return a


def plot_poles(
    path,
    eigenvalues,
    region=None,
    *,
    plant_poles=None,
    title: str = "Observer error poles and design region",
    size: tuple[int, int] = DEFAULT_SIZE,
    overwrite: bool = False,
) -> pathlib.Path:
    """Eigenvalues in the complex plane with the design region shaded.

    **Arguments:**

    - `path`: PNG file to write.
    - `eigenvalues`: error-dynamics eigenvalues (e.g. ``design.report.eigenvalues``).
    - `region`: a `fojax.Disk`, `HalfPlane`, `Sector` or intersection; its interior
      (where `region.margin > 0`) is shaded and its boundary drawn, so every region
      type, intersections included, is drawn exactly.
    - `plant_poles`: optional finite poles of the plant (drawn as crosses).
    - `title`, `size` (pixels), `overwrite`.

    **Returns:** the PNG path.
    """
    eigs = np.atleast_1d(np.asarray(eigenvalues, dtype=complex))
    pts = [eigs]
    if plant_poles is not None:
        pts.append(np.atleast_1d(np.asarray(plant_poles, dtype=complex)))
    allp = np.concatenate(pts) if pts else np.zeros(0, complex)
    re = list(allp.real) + [0.0]
    im = list(allp.imag) + [0.0]
    from ..design import Disk, Intersection

    parts = region.parts if isinstance(region, Intersection) else (region,) if region else ()
    for p in parts:
        if isinstance(p, Disk):
            re += [p.center - p.radius, p.center + p.radius]
            im += [-p.radius, p.radius]
    xmin, xmax = min(re), max(re)
    span = max(xmax - xmin, max(abs(v) for v in im) * 2, 1.0)
    xmin, xmax = xmin - 0.15 * span, xmax + 0.15 * span
    ymax = max(max(abs(v) for v in im), 0.5 * (xmax - xmin) * size[1] / size[0]) * 1.1
    fig = _figure(size)
    ax = fig.add_subplot(1, 1, 1)
    if region is not None:
        X, Y = np.meshgrid(np.linspace(xmin, xmax, 400), np.linspace(-ymax, ymax, 300))
        M = np.asarray(region.margin(X + 1j * Y), dtype=float)
        ax.contourf(X, Y, M, levels=[0.0, np.inf], colors=["tab:green"], alpha=0.25)
        ax.contour(X, Y, M, levels=[0.0], colors=["tab:green"], linewidths=1.5)
        ax.plot([], [], color="tab:green", lw=6, alpha=0.4, label=f"region: {region.describe()}")
    ax.axvline(0.0, color="k", lw=0.8)
    ax.axhline(0.0, color="k", lw=0.5)
    if plant_poles is not None:
        pp = np.atleast_1d(np.asarray(plant_poles, dtype=complex))
        ax.plot(pp.real, pp.imag, "x", color="tab:red", ms=9, mew=2, label="plant poles")
    ax.plot(eigs.real, eigs.imag, "o", color="tab:blue", ms=7, label="observer error poles")
    ax.set_xlim(xmin, xmax)
    ax.set_ylim(-ymax, ymax)
    ax.set_xlabel("Re s")
    ax.set_ylabel("Im s")
    ax.set_title(title)
    ax.legend(loc="best", fontsize=8)
    ax.grid(alpha=0.3)
    fig.tight_layout()
    return _save(fig, path, overwrite)


def plot_estimates(
    path,
    ts,
    truth,
    estimates: Mapping[str, Sequence],
    *,
    labels: Sequence[str] | None = None,
    band_label: str = "5–95 % band",
    truth_label: str = "truth",
    title: str = "Estimates vs truth (Monte Carlo)",
    size: tuple[int, int] = DEFAULT_SIZE,
    overwrite: bool = False,
) -> pathlib.Path:
    """True functionals and estimates with Monte Carlo confidence bands, one panel per
    component.

    **Arguments:**

    - `path`: PNG file to write.
    - `ts`: ``(T,)`` time grid.
    - `truth`: ``(T, q)`` (or ``(T,)``) true values, e.g. of the nominal sample or the median.
    - `estimates`: ``{observer name: (lower, median, upper)}``, each ``(T, q)``: the
      quantiles of the estimate over the Monte Carlo samples.
    - `labels`: names of the ``q`` components (default ``z1``, ``z2``, …).
    - `band_label`, `truth_label`, `title`, `size` (pixels), `overwrite`.

    **Returns:** the PNG path.
    """
    ts = np.asarray(ts, dtype=float)
    truth = _as_2d("truth", truth, len(ts))
    q = truth.shape[1]
    labels = list(labels) if labels is not None else [f"z{i + 1}" for i in range(q)]
    fig = _figure(size)
    axes = fig.subplots(q, 1, sharex=True, squeeze=False)[:, 0]
    colors = ["tab:blue", "tab:orange", "tab:green", "tab:purple", "tab:brown"]
    for i, ax in enumerate(axes):
        ax.plot(ts, truth[:, i], color="k", lw=1.5, label=truth_label)
        for j, (name, (lo, med, hi)) in enumerate(estimates.items()):
            lo, med, hi = (_as_2d(f"estimates[{name!r}]", a, len(ts)) for a in (lo, med, hi))
            c = colors[j % len(colors)]
            ax.fill_between(ts, lo[:, i], hi[:, i], color=c, alpha=0.25, label=f"{name} {band_label}")
            ax.plot(ts, med[:, i], color=c, lw=1.2, ls="--", label=f"{name} median")
        ax.set_ylabel(labels[i])
        ax.grid(alpha=0.3)
    axes[-1].set_xlabel("t [s]")
    # one legend for all panels, between the title and the first panel (inside a panel it
    # hid the curves it explains)
    handles, names = axes[0].get_legend_handles_labels()
    ncol = min(len(names), 4)
    rows = -(-len(names) // ncol)
    fig.suptitle(title)
    fig.legend(handles, names, loc="upper center", bbox_to_anchor=(0.5, 0.955), ncol=ncol, fontsize=7,
               frameon=False)
    fig.tight_layout(rect=(0, 0, 1, 0.95 - 0.032 * rows))
    return _save(fig, path, overwrite)


def plot_error_distributions(
    path,
    errors: Mapping[str, Sequence],
    *,
    kind: str = "box",
    ylabel: str = "IAE of the estimation error",
    title: str = "Error distribution per observer",
    log: bool = False,
    size: tuple[int, int] = DEFAULT_SIZE,
    overwrite: bool = False,
) -> pathlib.Path:
    """Box or violin plot of a per-sample error metric, one box per observer.

    **Arguments:**

    - `path`: PNG file to write.
    - `errors`: ``{observer name: (samples,) array}`` of a scalar metric per Monte
      Carlo sample (e.g. IAE); ``(samples, q)`` arrays are summed over components.
    - `kind`: ``"box"`` or ``"violin"``.
    - `ylabel`, `title`, `log` (logarithmic y axis), `size` (pixels), `overwrite`.

    **Returns:** the PNG path.
    """
    if kind not in ("box", "violin"):
        raise ValueError(f"kind must be 'box' or 'violin', got {kind!r}")
    names = list(errors)
    data = []
    for name in names:
        a = np.asarray(errors[name], dtype=float)
        data.append(a.reshape(a.shape[0], -1).sum(axis=1) if a.ndim > 1 else a.ravel())
    fig = _figure(size)
    ax = fig.add_subplot(1, 1, 1)
    pos = np.arange(1, len(names) + 1)
    if kind == "box":
        ax.boxplot(data, positions=pos, widths=0.6)
    else:
        ax.violinplot(data, positions=pos, showmedians=True)
    ax.set_xticks(pos)
    ax.set_xticklabels(names)
    if log:
        ax.set_yscale("log")
    ax.set_ylabel(ylabel)
    ax.set_title(title)
    ax.grid(alpha=0.3, axis="y")
    fig.tight_layout()
    return _save(fig, path, overwrite)


def plot_tuning_curve(
    path,
    steps,
    train,
    heldout=None,
    *,
    ylabel: str = "loss",
    title: str = "Tuning curve",
    log: bool = True,
    size: tuple[int, int] = DEFAULT_SIZE,
    overwrite: bool = False,
) -> pathlib.Path:
    """Training (and held-out) loss against the optimisation step.

    **Arguments:**

    - `path`: PNG file to write.
    - `steps`: ``(k,)`` step numbers.
    - `train`: ``(k,)`` training loss; `heldout`: optional ``(k,)`` held-out loss.
    - `ylabel`, `title`, `log` (logarithmic y axis when all values are positive),
      `size` (pixels), `overwrite`.

    **Returns:** the PNG path.
    """
    steps = np.asarray(steps, dtype=float)
    train = np.asarray(train, dtype=float)
    fig = _figure(size)
    ax = fig.add_subplot(1, 1, 1)
    ax.plot(steps, train, "-o", ms=3, label="train")
    vals = [train]
    if heldout is not None:
        heldout = np.asarray(heldout, dtype=float)
        ax.plot(steps, heldout, "-s", ms=3, label="held-out")
        vals.append(heldout)
    if log and all(np.all(v > 0) for v in vals):
        ax.set_yscale("log")
    ax.set_xlabel("step")
    ax.set_ylabel(ylabel)
    ax.set_title(title)
    ax.legend(loc="best")
    ax.grid(alpha=0.3)
    fig.tight_layout()
    return _save(fig, path, overwrite)
