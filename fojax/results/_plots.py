"""Figures for notebooks and papers: poles with the design region, estimates with Monte
Carlo bands, error distributions per observer, and the tuning curve.

Every ``plot_*`` function follows one convention:

- `ax=None` (default): it draws on a new `matplotlib.figure.Figure` of ``size`` pixels
  (default 800x600). The figure is not registered with `matplotlib.pyplot` (no global
  state, nothing to close): in a notebook it displays as the cell's value.
- `ax=` an existing `matplotlib.axes.Axes` (`plot_estimates`: one Axes per component):
  it draws into it and leaves the rest of that figure (its size, layout and other axes)
  to you; the legend and title go on that Axes.
- It **returns the Figure** drawn on (``ax.figure`` when `ax` is given), as
  `plot_estimates`, which may fill several panels, must; ``fig.axes`` lists its axes. (A
  figure made with `matplotlib.pyplot` shows itself in a notebook already: end the line
  with ``;`` not to see it twice.)
- It writes a file only when `path=` is given, in the format of the file's suffix (any
  format Matplotlib writes: ``.png``, ``.pdf``, ``.svg``, ``.eps``, ...), atomically
  (`fojax.results.atomic_write_bytes`: never outside a results folder a write is confined
  to); an existing file is replaced only with ``overwrite=True``.

Plotting needs Matplotlib, an optional dependency: ``pip install 'fojax[plot]'``.

!!! example

    ```python
    import fojax.results as fr

    fig = fr.plot_poles(design.report.eigenvalues, design.region)   # a new Figure
    fr.plot_poles(design.report.eigenvalues, design.region, ax=my_ax)  # into my_ax
    fr.plot_poles(design.report.eigenvalues, design.region, path="poles.pdf")
    ```
"""

from __future__ import annotations

import io
import pathlib
from collections.abc import Mapping, Sequence

import numpy as np

from .._linalg import clusters
from ._io import atomic_write_bytes


DEFAULT_SIZE = (800, 600)
_DPI = 100

PLOT_EXTRA = "plotting needs matplotlib, an optional dependency of fojax: pip install 'fojax[plot]'"


def matplotlib_available() -> bool:
    """Whether Matplotlib can be imported (the ``plot`` extra is installed)."""
    try:
        import matplotlib  # noqa: F401
    except ImportError:
        return False
    return True


def _require_matplotlib():
    try:
        import matplotlib  # noqa: F401
    except ImportError as err:
        raise ImportError(PLOT_EXTRA) from err


def _figure(size, *, layout: str | None = None):
    _require_matplotlib()
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    w, h = size
    fig = Figure(figsize=(w / _DPI, h / _DPI), dpi=_DPI, layout=layout)
    FigureCanvasAgg(fig)
    return fig


def _check_axes(ax, n: int = 1) -> list:
    """`ax` as a list of `n` Matplotlib Axes (a clear error for anything else)."""
    _require_matplotlib()
    from matplotlib.axes import Axes

    axes = [ax] if isinstance(ax, Axes) else list(ax) if isinstance(ax, Sequence | np.ndarray) else [ax]
    if len(axes) != n or not all(isinstance(a, Axes) for a in axes):
        raise TypeError(
            f"ax must be {'a matplotlib Axes' if n == 1 else f'{n} matplotlib Axes (one per component)'}"
            f" or None (a new Figure); got {type(ax).__name__}"
            + (f" of length {len(axes)}" if isinstance(ax, Sequence | np.ndarray) else "")
        )
    return axes


def _figure_and_axes(ax, size, n: int = 1, *, layout: str | None = "constrained", sharex: bool = False):
    """``(fig, axes, own)``: a new Figure of ``size`` pixels with `n` stacked axes when `ax`
    is None (``own``: its legend, title and layout are ours to arrange), else `ax`'s."""
    if ax is None:
        fig = _figure(size, layout=layout)
        axes = list(fig.subplots(n, 1, sharex=sharex, squeeze=False)[:, 0])
        return fig, axes, True
    axes = _check_axes(ax, n)
    return axes[0].figure, axes, False


def _save(fig, path, overwrite: bool) -> pathlib.Path:
    """Write `fig` to `path` in the format of its suffix, atomically."""
    path = pathlib.Path(path)
    fmt = path.suffix[1:].lower()
    if fig.canvas is None or not hasattr(fig.canvas, "get_supported_filetypes"):
        from matplotlib.backends.backend_agg import FigureCanvasAgg

        FigureCanvasAgg(fig)
    formats = fig.canvas.get_supported_filetypes()
    if fmt not in formats:
        raise ValueError(
            f"path={str(path)!r}: cannot tell the file format from its suffix {path.suffix!r}; give one "
            f"Matplotlib writes: {', '.join('.' + f for f in sorted(formats))}"
        )
    buf = io.BytesIO()
    # the figure's own dpi and no bbox_inches: a figure made here keeps its exact pixel size
    fig.savefig(buf, format=fmt, dpi="figure")
    return atomic_write_bytes(path, buf.getvalue(), overwrite=overwrite)


def _finish(fig, path, overwrite: bool):
    if path is not None:
        _save(fig, path, overwrite)
    return fig


def _as_2d(name, a, T=None):
    a = np.asarray(a, dtype=float)
    if a.ndim == 1:
        a = a[:, None]
    if a.ndim != 2 or (T is not None and a.shape[0] != T):
        raise ValueError(f"{name} must have shape (len(ts), q) or (len(ts),); got {a.shape}")
    return a


# ------------------------------------------------------------------ pole plots
# Every region of fojax.design is convex (disk, half-plane, sector with damping > 0, and
# their intersections), so it is drawn as a convex polygon: each part is clipped to a large
# box around the plot, and an intersection is the polygon of one part clipped by the others
# (Sutherland-Hodgman). The box is far larger than any window the plot shows, so its edges
# are never visible; the maths of the regions (fojax.design._regions) is not duplicated
# beyond their defining parameters, and the polygon is checked against `region.margin` in
# the tests.
POLE_MULTIPLICITY_RTOL = 1e-3
"""Poles closer than this fraction of the poles' scale (the largest modulus of the poles
drawn) are one marker annotated with their multiplicity ("×2"): at any readable plot size
they would be one dot."""

_DISK_VERTICES = 720


def _clip(poly: np.ndarray, a: np.ndarray, b: float) -> np.ndarray:
    """The part of the convex polygon `poly` ((k, 2) vertices) where ``a · p <= b``
    (one Sutherland-Hodgman pass, vectorised: each vertex p is kept where ``a·p <= b``, and
    followed by the crossing point of the edge to the next vertex where that edge crosses
    the line)."""
    if len(poly) == 0:
        return poly
    q = np.roll(poly, -1, axis=0)
    vp = poly @ a - b
    vq = np.roll(vp, -1)
    cross = ((vp < 0) & (vq > 0)) | ((vq < 0) & (vp > 0))
    frac = np.divide(vp, vp - vq, out=np.zeros_like(vp), where=cross)
    points = np.stack([poly, poly + (q - poly) * frac[:, None]], axis=1).reshape(-1, 2)
    return points[np.stack([vp <= 0, cross], axis=1).reshape(-1)]


def _part_halfspaces(part) -> list[tuple[np.ndarray, float]]:
    """Half-spaces ``a · p <= b`` whose intersection is `part` (a disk: its inscribed
    regular polygon of `_DISK_VERTICES` sides)."""
    from ..design import Disk, HalfPlane, Sector

    if isinstance(part, Disk):
        phi = np.linspace(0.0, 2 * np.pi, _DISK_VERTICES, endpoint=False) + np.pi / _DISK_VERTICES
        # the polygon through the circle's points at angles phi: edge normals at angles phi
        r = part.radius * np.cos(np.pi / _DISK_VERTICES)
        return [(np.array([np.cos(t), np.sin(t)]), part.center * np.cos(t) + r) for t in phi]
    if isinstance(part, HalfPlane):
        return [(np.array([1.0, 0.0]), -part.decay)]
    if isinstance(part, Sector):
        th = np.arccos(part.damping)
        # -Re(s) sin θ - |Im s| cos θ >= 0  <=>  x sin θ ± y cos θ <= 0
        return [(np.array([np.sin(th), np.cos(th)]), 0.0), (np.array([np.sin(th), -np.cos(th)]), 0.0)]
    raise TypeError(f"cannot draw a region of type {type(part).__name__}")


def _region_polygon(region, box: float, center=(0.0, 0.0)) -> np.ndarray:
    """The region (a part or an intersection) clipped to the square of half-width `box`
    around `center`, as the ``(k, 2)`` vertices of a convex polygon (empty if the region
    does not meet the square)."""
    from ..design import Intersection

    cx, cy = center
    poly = np.array([[cx - box, cy - box], [cx + box, cy - box], [cx + box, cy + box], [cx - box, cy + box]])
    parts = region.parts if isinstance(region, Intersection) else (region,)
    for part in parts:
        for a, b in _part_halfspaces(part):
            poly = _clip(poly, a, b)
    return poly


def _part_boundary(part, far: float):
    """``(xs, ys, label)`` of the boundary of one region part, drawn out to distance `far`."""
    from ..design import Disk, HalfPlane, Sector

    if isinstance(part, Disk):
        t = np.linspace(0, 2 * np.pi, 361)
        return (part.center + part.radius * np.cos(t), part.radius * np.sin(t),
                f"disk: |s − ({part.center:g})| < {part.radius:g}")
    if isinstance(part, HalfPlane):
        return (np.array([-part.decay, -part.decay]), np.array([-far, far]),
                f"decay: Re s < {-part.decay:g}")
    if isinstance(part, Sector):
        th = np.arccos(part.damping)
        x, y = -far * np.cos(th), far * np.sin(th)
        return (np.array([x, 0.0, x]), np.array([y, 0.0, -y]),
                f"damping ≥ {part.damping:g} (sector, ±{np.degrees(th):.1f}°)")
    raise TypeError(f"cannot draw a region of type {type(part).__name__}")


def _draw_poles(ax, own: bool, eigenvalues, region=None, *, plant_poles=None,
                title: str = "Observer error poles and design region"):
    from matplotlib.patches import Polygon

    from ..design import Disk, HalfPlane, Intersection, Sector

    eigs = np.atleast_1d(np.asarray(eigenvalues, dtype=complex)).ravel()
    pp = (np.zeros(0, complex) if plant_poles is None
          else np.atleast_1d(np.asarray(plant_poles, dtype=complex)).ravel())
    allp = np.concatenate([eigs, pp])
    allp = allp[np.isfinite(allp)]
    scale = float(np.max(np.abs(allp))) if allp.size else 0.0
    scale = scale if scale > 0 else 1.0
    tol = POLE_MULTIPLICITY_RTOL * scale

    # --- the window: every pole, the origin, the region if bounded, else its boundary anchors
    pts = [complex(0.0)] + list(allp)
    parts = () if region is None else (region.parts if isinstance(region, Intersection) else (region,))
    far = 1e3 * max(scale, 1.0, *(abs(getattr(p, "center", 0.0)) + getattr(p, "radius", 0.0)
                                  + getattr(p, "decay", 0.0) for p in parts))
    exact = all(isinstance(p, Disk | HalfPlane | Sector) for p in parts)  # else: a user's own region
    poly = _region_polygon(region, far) if region is not None and exact else np.zeros((0, 2))
    bounded = poly.size and np.max(np.abs(poly)) < 0.5 * far
    if region is not None and bounded:
        pts += [complex(x, y) for x, y in poly[:: max(1, len(poly) // 90)]]
        pts += [complex(poly[:, 0].min(), 0.0), complex(poly[:, 0].max(), 0.0)]
    elif region is not None:
        for p in parts:  # unbounded: show each boundary where it meets the real axis
            if isinstance(p, HalfPlane):
                pts += [complex(-p.decay, 0.0), complex(-p.decay - max(1.0, p.decay), 0.0)]
            elif isinstance(p, Disk):
                pts += [complex(p.center - p.radius, -p.radius), complex(p.center + p.radius, p.radius)]
        if len(pts) == 1 or max(abs(z) for z in pts) == 0:
            pts += [complex(-1.0, 0.0)]
        pts += [complex(min(z.real for z in pts), 0.0)]
    if region is not None and not exact:  # a user's region: in view if a coarse scan finds it bounded
        re, im = np.array([z.real for z in pts]), np.abs([z.imag for z in pts])
        c, h = 0.5 * (re.min() + re.max()), 3.0 * max(re.max() - re.min(), 2 * im.max(), 1.0)
        X, Y = np.meshgrid(np.linspace(c - h, c + h, 241), np.linspace(-h, h, 241))
        inside = np.asarray(region.margin(X + 1j * Y), dtype=float) > 0
        border = inside[0].any() or inside[-1].any() or inside[:, 0].any() or inside[:, -1].any()
        if inside.any() and not border:
            pts += [complex(X[inside].min(), Y[inside].max()), complex(X[inside].max(), Y[inside].min())]
    re = np.array([z.real for z in pts])
    im = np.abs(np.array([z.imag for z in pts]))
    xmin, xmax, ymax = re.min(), re.max(), im.max()
    span = max(xmax - xmin, 2 * ymax)
    span = span if span > 0 else scale  # every point at the origin
    pad = 0.12 * span
    xlim, ylim = (xmin - pad, xmax + pad), (-(ymax + pad), ymax + pad)

    fig = ax.figure
    if region is not None:
        face = (0.17, 0.63, 0.17, 0.25)
        if poly.size:  # the region itself: shaded, with its boundary as a solid line
            ax.add_patch(Polygon(poly, closed=True, facecolor=face,
                                 edgecolor="darkgreen", lw=2.0, label=f"region: {region.describe()}",
                                 zorder=1))
        elif not exact:  # a region class fojax does not know: its margin > 0 on a grid
            xc, half = 0.5 * (xlim[0] + xlim[1]), 3.0 * max(xlim[1] - xlim[0], ylim[1] - ylim[0])
            X, Y = np.meshgrid(np.linspace(xc - half, xc + half, 900), np.linspace(-half, half, 900))
            M = np.asarray(region.margin(X + 1j * Y), dtype=float)
            ax.contourf(X, Y, M, levels=[0.0, np.inf], colors=[face], zorder=1)
            ax.contour(X, Y, M, levels=[0.0], colors=["darkgreen"], linewidths=2.0, zorder=1)
            ax.fill([], [], facecolor=face, edgecolor="darkgreen", lw=2.0,
                    label=f"region: {region.describe()}")  # its legend entry (draws nothing)
        else:
            ax.plot([], [], " ", label=f"region: {region.describe()} (empty)")
        if len(parts) > 1:  # an intersection: where each constraint's boundary runs
            styles = ["--", "-.", ":", (0, (5, 2, 1, 2))]
            for k, part in enumerate(p for p in parts if isinstance(p, Disk | HalfPlane | Sector)):
                xs, ys, label = _part_boundary(part, far)
                ax.plot(xs, ys, color="tab:green", lw=1.0, ls=styles[k % len(styles)], label=label, zorder=1)
    ax.axvline(0.0, color="k", lw=0.8, zorder=0.5)
    ax.axhline(0.0, color="k", lw=0.5, zorder=0.5)

    def _markers(z, fmt, color, ms, label, **kw):
        groups = clusters(z, tol)
        pos = np.array([z[g].mean() for g in groups]) if groups else np.zeros(0, complex)
        mult = np.array([len(g) for g in groups], dtype=int)
        if pos.size:
            ax.plot(pos.real, pos.imag, fmt, color=color, ms=ms, ls="none",
                    label=label + (f" (×k: k poles within {tol:.1g})" if (mult > 1).any() else ""),
                    zorder=3, **kw)
        for zz, m in zip(pos, mult):
            if m > 1:
                ax.annotate(f"×{m}", (zz.real, zz.imag), xytext=(6, 6), textcoords="offset points",
                            color=color, fontsize=10, fontweight="bold", zorder=4, gid="pole-multiplicity")
        return pos, mult

    if pp.size:
        _markers(pp, "x", "tab:red", 9, "plant poles", mew=2)
    _markers(eigs, "o", "tab:blue", 7, "observer error poles", mfc="none", mew=1.8)
    ax.set_xlim(*xlim)
    ax.set_ylim(*ylim)
    ax.set_xlabel("Re s")
    ax.set_ylabel("Im s")
    ax.set_title(title)
    ax.grid(alpha=0.3)
    handles, labels = ax.get_legend_handles_labels()
    if own:  # below the axes, outside them (the layout reserves its room)
        fig.legend(handles, labels, loc="outside lower center", ncol=1 if len(labels) > 3 else 2,
                   fontsize=9, frameon=False)
    else:
        ax.legend(handles, labels, fontsize=9, loc="best")
    # Equal axes (a disk is a circle, a sector's rays have their true angle) without
    # wasting the figure: widen the shorter direction of the window to the shape of the
    # axes box the layout gives, then fix the aspect (the limits only ever grow, so
    # everything chosen above stays visible).
    fig.draw_without_rendering()  # runs the layout: the axes box is final
    bbox = ax.get_window_extent()
    (x0, x1), (y0, y1) = xlim, ylim
    want = bbox.width / max(bbox.height, 1.0)  # data width / data height at equal scales
    if (x1 - x0) / (y1 - y0) < want:
        half = 0.5 * want * (y1 - y0)
        xc = 0.5 * (x0 + x1)
        ax.set_xlim(xc - half, xc + half)
    else:
        half = 0.5 * (x1 - x0) / want
        ax.set_ylim(-half, half)
    ax.set_aspect("equal", adjustable="box")


def plot_poles(
    eigenvalues,
    region=None,
    *,
    plant_poles=None,
    title: str = "Observer error poles and design region",
    ax=None,
    path=None,
    size: tuple[int, int] = DEFAULT_SIZE,
    overwrite: bool = False,
):
    """Eigenvalues in the complex plane with the design region shaded, on equal axes (a
    disk is drawn as a circle, a damping sector with its true angle).

    **Arguments:**

    - `eigenvalues`: error-dynamics eigenvalues (e.g. ``design.report.eigenvalues``).
    - `region`: a `fojax.Disk`, `HalfPlane`, `Sector` or intersection. The region is
      shaded (an intersection: the intersection itself) and the boundary of every part
      drawn (circle, vertical line, the two rays of a sector), each named in the legend.
      The window holds every pole and the whole region when it is bounded; for an
      unbounded region it shows the poles, the origin and where each boundary meets the
      real axis.
    - `plant_poles`: optional finite poles of the plant (drawn as crosses).
    - `title`: the axes' title.
    - `ax`: a Matplotlib Axes to draw into (its figure keeps its layout; the legend goes
      inside the axes), or None for a new Figure of `size` pixels (legend below the axes).
    - `path`: optional file to write the figure to (format from the suffix: ``.png``,
      ``.pdf``, ``.svg``, ...); `overwrite`: whether an existing file may be replaced.

    Poles closer to each other than `POLE_MULTIPLICITY_RTOL` (1e-3) times the largest
    pole modulus are one marker annotated "×k" (a double pole is not a single dot).

    **Returns:** the `matplotlib.figure.Figure` drawn on.

    **Raises:** `ImportError` without Matplotlib (``pip install 'fojax[plot]'``);
    `FileExistsError` if `path` exists and not `overwrite`; `ValueError` for a suffix
    Matplotlib cannot write.
    """
    fig, (ax,), own = _figure_and_axes(ax, size)
    _draw_poles(ax, own, eigenvalues, region, plant_poles=plant_poles, title=title)
    return _finish(fig, path, overwrite)


def plot_estimates(
    ts,
    truth,
    estimates: Mapping[str, Sequence],
    *,
    labels: Sequence[str] | None = None,
    band_label: str = "5–95 % band",
    truth_label: str = "truth",
    title: str = "Estimates vs truth (Monte Carlo)",
    ax=None,
    path=None,
    size: tuple[int, int] = DEFAULT_SIZE,
    overwrite: bool = False,
):
    """True functionals and estimates with Monte Carlo confidence bands, one panel per
    component.

    **Arguments:**

    - `ts`: ``(T,)`` time grid.
    - `truth`: ``(T, q)`` (or ``(T,)``) true values, e.g. of the nominal sample or the median.
    - `estimates`: ``{observer name: (lower, median, upper)}``, each ``(T, q)``: the
      quantiles of the estimate over the Monte Carlo samples.
    - `labels`: names of the ``q`` components (default ``z1``, ``z2``, …).
    - `band_label`, `truth_label`, `title`.
    - `ax`: ``q`` Matplotlib Axes (a single Axes when ``q = 1``) to draw the panels into
      (legend in the first, title on it), or None for a new Figure of `size` pixels (one
      legend below the panels, title above them).
    - `path`: optional file to write the figure to (format from the suffix);
      `overwrite`: whether an existing file may be replaced.

    **Returns:** the `matplotlib.figure.Figure` drawn on.

    **Raises:** `ValueError` for arrays of another shape; as `plot_poles` otherwise.
    """
    ts = np.asarray(ts, dtype=float)
    truth = _as_2d("truth", truth, len(ts))
    q = truth.shape[1]
    fig, axes, own = _figure_and_axes(ax, size, q, sharex=True)
    labels = list(labels) if labels is not None else [f"z{i + 1}" for i in range(q)]
    colors = ["tab:blue", "tab:orange", "tab:green", "tab:purple", "tab:brown"]
    handles, names = [], []
    for i, ax in enumerate(axes):
        (truth_line,) = ax.plot(ts, truth[:, i], color="k", lw=1.5, label=truth_label)
        if i == 0:
            handles.append(truth_line)
            names.append(truth_label)
        for j, (name, (lo, med, hi)) in enumerate(estimates.items()):
            lo, med, hi = (_as_2d(f"estimates[{name!r}]", a, len(ts)) for a in (lo, med, hi))
            c = colors[j % len(colors)]
            band = ax.fill_between(ts, lo[:, i], hi[:, i], color=c, alpha=0.25, label=f"{name} {band_label}")
            (line,) = ax.plot(ts, med[:, i], color=c, lw=1.2, ls="--", label=f"{name} median")
            if i == 0:  # one legend entry per observer: its band with its median drawn on it
                handles.append((band, line))
                names.append(f"{name}: median and {band_label}")
        ax.set_ylabel(labels[i])
        ax.grid(alpha=0.3)
    axes[-1].set_xlabel("t [s]")
    if own:
        fig.suptitle(title)
        # One legend for all panels, in normal type, directly below the panels (the layout
        # reserves its room), where it hides no curve.
        ncol = min(len(names), 2 if max((len(n) for n in names), default=0) > 24 else 4)
        fig.legend(handles, names, loc="outside lower center", ncol=max(ncol, 1), frameon=False)
    else:
        axes[0].set_title(title)
        axes[0].legend(handles, names, loc="best")
    return _finish(fig, path, overwrite)


def plot_error_distributions(
    errors: Mapping[str, Sequence],
    *,
    kind: str = "box",
    ylabel: str = "IAE of the estimation error",
    title: str = "Error distribution per observer",
    log: bool = False,
    ax=None,
    path=None,
    size: tuple[int, int] = DEFAULT_SIZE,
    overwrite: bool = False,
):
    """Box or violin plot of a per-sample error metric, one box per observer.

    **Arguments:**

    - `errors`: ``{observer name: (samples,) array}`` of a scalar metric per Monte
      Carlo sample (e.g. IAE); ``(samples, q)`` arrays are summed over components.
    - `kind`: ``"box"`` or ``"violin"``.
    - `ylabel`, `title`, `log` (logarithmic y axis).
    - `ax`: a Matplotlib Axes to draw into, or None for a new Figure of `size` pixels.
    - `path`: optional file to write the figure to (format from the suffix);
      `overwrite`: whether an existing file may be replaced.

    **Returns:** the `matplotlib.figure.Figure` drawn on.

    **Raises:** `ValueError` for an unknown `kind`; as `plot_poles` otherwise.
    """
    if kind not in ("box", "violin"):
        raise ValueError(f"kind must be 'box' or 'violin', got {kind!r}")
    names = list(errors)
    data = []
    for name in names:
        a = np.asarray(errors[name], dtype=float)
        data.append(a.reshape(a.shape[0], -1).sum(axis=1) if a.ndim > 1 else a.ravel())
    fig, (ax,), own = _figure_and_axes(ax, size, layout=None)
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
    if own:
        fig.tight_layout()
    return _finish(fig, path, overwrite)


def plot_tuning_curve(
    steps,
    train,
    heldout=None,
    *,
    heldout_before: float | None = None,
    heldout_after: float | None = None,
    ylabel: str = "loss",
    title: str = "Tuning curve",
    log: bool = True,
    ax=None,
    path=None,
    size: tuple[int, int] = DEFAULT_SIZE,
    overwrite: bool = False,
):
    """Training (and held-out) loss against the optimisation step.

    **Arguments:**

    - `steps`: ``(k,)`` step numbers.
    - `train`: ``(k,)`` training loss; `heldout`: optional ``(k,)`` held-out loss (``nan``
      where it was not evaluated).
    - `heldout_before`: the held-out loss of the starting design (before tuning, e.g.
      `TuneResult.initial_heldout`): a marked point at step 0, which starts the held-out
      curve, and a dotted reference line across the plot.
    - `heldout_after`: the held-out loss of the returned design (`TuneResult.final_heldout`):
      a marked point at the last step.
    - `ylabel`, `title`, `log` (logarithmic y axis when all values are positive).
    - `ax`: a Matplotlib Axes to draw into, or None for a new Figure of `size` pixels.
    - `path`: optional file to write the figure to (format from the suffix);
      `overwrite`: whether an existing file may be replaced.

    **Returns:** the `matplotlib.figure.Figure` drawn on.

    **Raises:** as `plot_poles`.
    """
    steps = np.asarray(steps, dtype=float)
    train = np.asarray(train, dtype=float)
    fig, (ax,), _ = _figure_and_axes(ax, size)
    ax.plot(steps, train, "-o", ms=3, color="tab:blue", label="training loss")
    vals = [train[np.isfinite(train)]]
    hs, hv = np.zeros(0), np.zeros(0)
    if heldout is not None:
        heldout = np.asarray(heldout, dtype=float)
        ok = np.isfinite(heldout)
        hs, hv = steps[ok], heldout[ok]
    if heldout_before is not None and np.isfinite(heldout_before):
        hs, hv = np.concatenate([[0.0], hs]), np.concatenate([[float(heldout_before)], hv])
    if hs.size:
        ax.plot(hs, hv, "-s", ms=3, color="tab:orange", label="held-out loss")
        vals.append(hv)
    last = float(steps[-1]) if steps.size else 0.0
    if heldout_before is not None and np.isfinite(heldout_before):
        b = float(heldout_before)
        ax.axhline(b, color="tab:orange", lw=0.8, ls=":")
        ax.plot([0.0], [b], "D", ms=8, color="tab:orange", mec="k", ls="none",
                label=f"held-out before tuning (step 0): {b:.4g}", zorder=3)
    if heldout_after is not None and np.isfinite(heldout_after):
        a = float(heldout_after)
        ax.plot([last], [a], "*", ms=14, color="tab:red", mec="k", ls="none",
                label=f"held-out after tuning (step {last:g}): {a:.4g}"
                + (f" ({100.0 * (a - float(heldout_before)) / float(heldout_before):+.1f} %)"
                   if heldout_before not in (None, 0.0) and np.isfinite(heldout_before) else ""),
                zorder=3)
        vals.append(np.array([a]))
    if log and all(np.all(v > 0) for v in vals):
        ax.set_yscale("log")
    ax.margins(x=0.03, y=0.08)  # the step-0 and last-step markers are not cut by the frame
    ax.set_xlabel("step")
    ax.set_ylabel(ylabel)
    ax.set_title(title)
    ax.legend(loc="best")
    ax.grid(alpha=0.3)
    return _finish(fig, path, overwrite)
