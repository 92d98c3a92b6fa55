"""`fojax.results`: saved designs (bit-exact round trip, every design class), atomic no-clobber
writes, results folders, the Markdown report and the figures.

Oracles:
- the design before saving: every array of the loaded design equals the saved one bit for bit
  (``np.array_equal``, same dtype and shape), every number of the report is the same, and the
  loaded observer gives identical vector fields, outputs and simulations, for every design class
  of `fojax.design` (generalized, Takagi–Sugeno, unknown-input, finite-time, fault-estimator);
  foreign membership classes named in a file are never imported;
- the files read back: Python's ``json``, the Markdown text, the PNG pixels (``matplotlib.image``);
- figures: each region's own pointwise test and Matplotlib's record of what an Axes holds
  (their sections below say which);
- files and folders: the POSIX rule for modes (``0o666 & ~umask``), pathlib's resolution of
  where a path lands, and hashlib's SHA-256 of the bytes read back.
"""

import dataclasses
import json
import os
import pathlib
import zipfile

import equinox as eqx
import jax
import jax.numpy as jnp
import matplotlib.image as mpimg
import numpy as np
import pytest
from helpers import assert_designs_identical

import fojax
from fojax.design import (
    design_fault_estimator,
    design_finite_time_observer,
    design_functional_observer,
    design_ts_observer,
    design_unknown_input_observer,
    Disk,
    FaultEstimatorDesign,
    FiniteTimeObserverDesign,
    FunctionalObserverDesign,
    HalfPlane,
    Sector,
    TakagiSugenoObserverDesign,
    UnknownInputObserverDesign,
)
from fojax.results import (
    atomic_write_text,
    load_design,
    new_results_folder,
    plot_error_distributions,
    plot_estimates,
    plot_poles,
    plot_tuning_curve,
    read_design_metadata,
    save_design,
    write_metrics,
    write_report,
)


@pytest.fixture(scope="module")
def design():
    ex = fojax.models.example_4_1_3()
    s = ex.system
    closed = fojax.DescriptorSystem(s.E, s.A + s.B @ jnp.asarray(ex.L), s.B, s.C)
    return design_functional_observer(closed, ex.L, kind="generalized", region=Disk(-2.0, 1.0))


def _all_arrays(d):
    out = {f"observer.{k}": getattr(d.observer, k) for k in "N J F H S G M P Q Wu Wy".split()}
    out |= {f"structure.{k}": getattr(d.structure, k) for k in "E A B C L R Eperp Z0 PiZ".split()}
    out |= {f"params.{k}": v for k, v in d.params.items()}
    out |= {k: getattr(d, k) for k in ("T", "K", "Z_eff", "X")}
    out["report.eigenvalues"] = d.report.eigenvalues
    return {k: np.asarray(v) for k, v in out.items()}


def test_save_load_bit_identical(design, tmp_path):
    path = save_design(design, tmp_path / "obs.npz", metadata={"config": "x.toml"})
    loaded = load_design(path)
    a, b = _all_arrays(design), _all_arrays(loaded)
    assert a.keys() == b.keys() and len(a) == 31
    for k in a:
        assert a[k].dtype == b[k].dtype and a[k].shape == b[k].shape, k
        assert np.array_equal(a[k], b[k]), k  # bit-identical (no tolerance)
    assert set(loaded.params) == set(design.params)
    assert loaded.kind == design.kind and loaded.observer.kind == design.observer.kind
    assert loaded.region == design.region
    assert loaded.structure.q1 == design.structure.q1 and loaded.structure.psi == design.structure.psi
    assert loaded.report.passed and loaded.report.to_dict() == design.report.to_dict()
    assert str(loaded.report) == str(design.report)
    meta = read_design_metadata(path)
    assert meta["fojax_version"] == fojax.__version__ and meta["user"] == {"config": "x.toml"}
    summary = meta["summary"]  # format 3: a readable summary beside the skeleton ("tree")
    assert summary["kind"] == "generalized" and summary["region"] == {"type": "disk", "center": -2.0, "radius": 1.0}
    assert "T" in meta["created"] and summary["report"]["passed"] is True and meta["format_version"] == 3
    # the loaded observer produces identical outputs on the same data
    rng = np.random.default_rng(0)
    o1, o2 = design.observer, loaded.observer
    xi = jnp.asarray(rng.normal(size=o1.state_size))
    u = jnp.asarray(rng.normal(size=2))
    y = jnp.asarray(rng.normal(size=3))
    assert np.array_equal(o1.vector_field(0.0, xi, u, y), o2.vector_field(0.0, xi, u, y))
    assert np.array_equal(o1.output(0.0, xi, u, y), o2.output(0.0, xi, u, y))


def test_loaded_observer_simulates_identically(design, tmp_path):
    loaded = load_design(save_design(design, tmp_path / "d.npz"))
    ex = fojax.models.example_4_1_3()
    plant = design.structure
    sys_ = fojax.DescriptorSystem(plant.E, plant.A, plant.B, plant.C)
    ts = jnp.linspace(0.0, 2.0, 21)
    s1 = fojax.simulate(sys_, jnp.asarray(ex.x0), ts, fojax.Step(jnp.array([1.0, 0.0])), observers=(design.observer,))
    s2 = fojax.simulate(sys_, jnp.asarray(ex.x0), ts, fojax.Step(jnp.array([1.0, 0.0])), observers=(loaded.observer,))
    assert np.array_equal(np.asarray(s1.estimates[0]), np.asarray(s2.estimates[0]))


def test_save_never_overwrites_silently(design, tmp_path):
    path = save_design(design, tmp_path / "obs.npz")
    before = path.read_bytes()
    with pytest.raises(FileExistsError, match=r"obs\.npz already exists.*overwrite=True"):
        save_design(design, path)
    assert path.read_bytes() == before
    save_design(design, path, overwrite=True)
    assert load_design(path).report.passed
    # no temporary files are left behind
    assert sorted(p.name for p in tmp_path.iterdir()) == ["obs.npz"]


def test_save_rejects_non_design_and_load_rejects_foreign_npz(tmp_path):
    with pytest.raises(TypeError, match="FunctionalObserverDesign"):
        save_design(object(), tmp_path / "x.npz")
    np.savez(tmp_path / "foreign.npz", a=np.zeros(2))
    with pytest.raises(fojax.errors.InputError, match="not a fojax design file"):
        load_design(tmp_path / "foreign.npz")


def test_atomic_write_text(tmp_path):
    p = atomic_write_text(tmp_path / "a.txt", "one")
    with pytest.raises(FileExistsError):
        atomic_write_text(p, "two")
    assert p.read_text() == "one"
    atomic_write_text(p, "two", overwrite=True)
    assert p.read_text() == "two"
    assert [q.name for q in tmp_path.iterdir()] == ["a.txt"]


def test_results_folders_are_never_reused(tmp_path):
    a = new_results_folder(tmp_path, prefix="run")
    (a / "keep.txt").write_text("first run")
    b = new_results_folder(tmp_path, prefix="run")
    assert a != b and a.is_dir() and b.is_dir() and a.name.startswith("run-")
    assert (a / "keep.txt").read_text() == "first run"
    c = new_results_folder(tmp_path, name="mine")
    (c / "x").write_text("1")
    with pytest.raises(FileExistsError, match="mine already exists and is not empty.*--overwrite"):
        new_results_folder(tmp_path, name="mine")
    assert new_results_folder(tmp_path, name="mine", overwrite=True) == c
    assert (c / "x").read_text() == "1"


def test_write_report_links_figures_and_numbers(tmp_path):
    png = tmp_path / "tune.png"
    plot_tuning_curve([0, 1, 2], [3.0, 2.0, 1.0], path=png)
    rep = write_report(
        tmp_path,
        title="Study",
        summary="Two observers.",
        numbers={"samples": 8, "IAE (generalized)": 1.234567},
        tables={"Comparison": (["observer", "IAE"], [["PO", 2.5], ["FGDO", 1.25]])},
        figures={"Tuning curve": png},
        files={"design": tmp_path / "d.npz"},
    )
    text = rep.read_text()
    assert text.startswith("# Study") and "![Tuning curve](tune.png)" in text
    assert "| IAE (generalized) | 1.235 |" in text and "| FGDO | 1.25 |" in text
    assert "[d.npz](d.npz)" in text and fojax.__version__ in text
    with pytest.raises(FileExistsError):
        write_report(tmp_path, title="again")


def _png(plot, path, *args, **kw):
    """Draw with `plot`, writing `path`; the image read back."""
    fig = plot(*args, path=path, **kw)
    assert fig.axes  # the Figure drawn on is returned
    return _img(path)


def _img(path):
    assert path.stat().st_size > 1000
    with open(path, "rb") as f:
        assert f.read(8) == b"\x89PNG\r\n\x1a\n"
    img = mpimg.imread(path)
    assert img.shape[:2] == (600, 800)  # default size 800x600 pixels
    assert img[..., :3].std() > 0.01  # not a blank image
    return img


def test_plot_poles_all_region_types(design, tmp_path):
    eigs = design.report.eigenvalues
    regions = [Disk(-2.0, 1.0), HalfPlane(1.0), Sector(0.6), Disk(-3.0, 2.0) & HalfPlane(1.5) & Sector(0.7)]
    imgs = [_png(plot_poles, tmp_path / f"p{i}.png", eigs, r, plant_poles=[1.79, -4.4 + 1.72j, -4.4 - 1.72j])
            for i, r in enumerate(regions)]
    for i in range(len(imgs)):
        for j in range(i):
            assert not np.array_equal(imgs[i], imgs[j])
    assert imgs[0].shape[2] in (3, 4)
    _png(plot_poles, tmp_path / "noregion.png", eigs)
    plot_poles(eigs, regions[0], size=(400, 300), path=tmp_path / "sz.png")
    assert mpimg.imread(tmp_path / "sz.png").shape[:2] == (300, 400)


def test_plot_estimates_bands(tmp_path):
    ts = np.linspace(0, 5, 200)
    truth = np.stack([np.sin(ts), np.cos(ts)], axis=1)
    est = {"PO": (truth - 0.3, truth + 0.05, truth + 0.4), "FGDO": (truth - 0.1, truth, truth + 0.1)}
    a = _png(plot_estimates, tmp_path / "a.png", ts, truth, est)
    b = _png(plot_estimates, tmp_path / "b.png", ts, truth, {"PO": (truth - 1, truth, truth + 1)})
    assert not np.array_equal(a, b)
    with pytest.raises(ValueError, match="truth must have shape"):
        plot_estimates(ts, truth[:10], est, path=tmp_path / "c.png")
    assert not (tmp_path / "c.png").exists()


def test_plot_error_distributions_box_and_violin(tmp_path):
    rng = np.random.default_rng(1)
    errs = {"PO": rng.gamma(2.0, 2.0, 50), "FGDO": rng.gamma(2.0, 0.5, 50)}
    a = _png(plot_error_distributions, tmp_path / "box.png", errs)
    b = _png(plot_error_distributions, tmp_path / "violin.png", errs, kind="violin")
    c = _png(plot_error_distributions, tmp_path / "box2.png", {"PO": errs["PO"] * 3, "FGDO": errs["FGDO"]})
    assert not np.array_equal(a, b) and not np.array_equal(a, c)
    with pytest.raises(ValueError, match="kind must be"):
        plot_error_distributions(errs, kind="pie")


def test_plot_tuning_curve(tmp_path):
    steps = np.arange(20)
    a = _png(plot_tuning_curve, tmp_path / "a.png", steps, np.exp(-steps / 5.0), np.exp(-steps / 6.0) + 0.01)
    b = _png(plot_tuning_curve, tmp_path / "b.png", steps, np.exp(-steps / 2.0))
    assert not np.array_equal(a, b)
    with pytest.raises(FileExistsError):
        plot_tuning_curve(steps, steps + 1.0, path=tmp_path / "a.png")
    assert os.path.getsize(tmp_path / "a.png") > 1000


def test_json_safe_metadata_is_valid_json(design, tmp_path):
    path = save_design(design, tmp_path / "m.npz")
    with np.load(path, allow_pickle=False) as data:
        meta = json.loads(str(data["__metadata__"][()]))
    assert meta["summary"]["sizes"] == {"n": 4, "m": 2, "p": 3, "q": 2, "q0": design.structure.q0}


def test_write_metrics_json_and_exact_npz(tmp_path):
    rng = np.random.default_rng(3)
    iae = rng.gamma(2.0, 1.0, 16)
    big = rng.normal(size=(20, 600))
    js, npz = write_metrics(
        tmp_path, {"PO": {"IAE": iae, "mean_IAE": float(iae.mean())}, "samples": 16, "note": "x", "traces": big}
    )
    meta = json.loads(js.read_text())
    assert meta["PO"]["IAE"] == iae.tolist() and meta["samples"] == 16 and meta["note"] == "x"
    assert meta["traces"] == {"shape": [20, 600], "npz_key": "traces"}
    with np.load(npz, allow_pickle=False) as data:
        assert np.array_equal(data["PO/IAE"], iae) and np.array_equal(data["traces"], big)
        assert float(data["PO/mean_IAE"]) == iae.mean()
    with pytest.raises(FileExistsError):
        write_metrics(tmp_path, {"a": 1.0})


# ------------------------------------------------------------------ figures by their artists
# Oracles: each region's own pointwise test `region.margin` (the shaded polygon must agree
# with it), the eigenvalues given (markers and multiplicities counted by hand), and the
# pixel boxes Matplotlib reports after drawing.
from matplotlib.path import Path as _MplPath  # noqa: E402


POLES = np.array([-2.0, -2.0 + 1e-9, -1.5 + 0.5j, -1.5 - 0.5j, -2.5])  # a double pole at -2
PLANT = np.array([1.79, -4.4 + 1.72j, -4.4 - 1.72j])
REGIONS = {
    "disk": Disk(-2.0, 1.0),
    "halfplane": HalfPlane(1.0),
    "sector": Sector(0.6),
    "intersection": Disk(-3.0, 2.0) & HalfPlane(1.5) & Sector(0.7),
    "unbounded-intersection": HalfPlane(1.0) & Sector(0.5),
}


def _boxes_disjoint(a, b):
    return a.x1 <= b.x0 or b.x1 <= a.x0 or a.y1 <= b.y0 or b.y1 <= a.y0


def _legend_checks(fig, axes):
    """The legend is inside the figure, overlaps no axes' data area, and uses normal type."""
    fig.canvas.draw()
    renderer = fig.canvas.get_renderer()
    [leg] = fig.legends
    box = leg.get_window_extent(renderer)
    W, H = fig.bbox.width, fig.bbox.height
    assert 0 <= box.x0 and box.x1 <= W and 0 <= box.y0 and box.y1 <= H
    for ax in axes:
        assert _boxes_disjoint(box, ax.get_window_extent(renderer))
    return [t.get_text() for t in leg.get_texts()], min(t.get_fontsize() for t in leg.get_texts())


@pytest.mark.parametrize("kind", list(REGIONS))
def test_pole_plot_equal_axes_region_drawn_and_everything_in_view(kind):
    region = REGIONS[kind]
    fig = plot_poles(POLES, region, plant_poles=PLANT)
    labels, fontsize = _legend_checks(fig, fig.axes)
    ax = fig.axes[0]
    (x0, x1), (y0, y1) = ax.get_xlim(), ax.get_ylim()
    box = ax.get_window_extent()
    # equal axes: one unit is as many pixels along Re as along Im
    assert ax.get_aspect() == 1.0
    assert (x1 - x0) / box.width == pytest.approx((y1 - y0) / box.height, rel=1e-3)
    # every pole is in view with a margin
    allp = np.concatenate([POLES, PLANT])
    pad = 0.02 * (x1 - x0)
    assert np.all((allp.real > x0 + pad) & (allp.real < x1 - pad) & (abs(allp.imag) < y1 - pad))
    # the shaded polygon is the region: agrees with region.margin on a grid of the view
    [patch] = ax.patches
    path = _MplPath(patch.get_xy())
    X, Y = np.meshgrid(np.linspace(x0, x1, 61), np.linspace(y0, y1, 47))
    s = (X + 1j * Y).ravel()
    m = region.margin(s)
    inside = path.contains_points(np.column_stack([s.real, s.imag]))
    clear = np.abs(m) > 0.02 * (x1 - x0)  # away from the boundary (the disk is a 720-gon)
    assert np.array_equal(inside[clear], m[clear] > 0)
    assert inside.any() and (~inside).any()  # region and its outside both visible
    verts = patch.get_xy()
    if np.max(np.abs(verts)) < 100:  # a bounded region: all of it in view
        assert verts[:, 0].min() >= x0 and verts[:, 0].max() <= x1
        assert verts[:, 1].min() >= y0 and verts[:, 1].max() <= y1
    else:  # unbounded: where each boundary meets the real axis is in view
        for part in getattr(region, "parts", (region,)):
            edge = -part.decay if isinstance(part, HalfPlane) else 0.0
            assert x0 < edge < x1
    # the legend names exactly what is drawn
    drawn = {a.get_label() for a in ax.lines + ax.patches if not a.get_label().startswith("_")}
    assert set(labels) == drawn
    assert f"region: {region.describe()}" in labels and fontsize >= 9
    parts = getattr(region, "parts", ())
    assert sum(lab.startswith(("disk:", "decay:", "damping")) for lab in labels) == len(parts)


def test_pole_plot_shows_multiplicities():
    fig = plot_poles(POLES, Disk(-2.0, 1.0), plant_poles=PLANT)
    ax = fig.axes[0]
    [observer] = [ln for ln in ax.lines if ln.get_label().startswith("observer error poles")]
    xs, ys = observer.get_data()
    assert len(xs) == 4  # 5 eigenvalues, the double one at -2 drawn once ...
    notes = [t for t in ax.texts if t.get_text().startswith("×")]
    assert [t.get_text() for t in notes] == ["×2"]  # ... and marked ×2 there
    assert notes[0].xy == pytest.approx((-2.0, 0.0), abs=1e-8)
    # a triple pole and distinct poles 0.05 apart (1 % of the scale) stay as they are
    fig = plot_poles([-1.0, -1.0, -1.0 + 1e-7, -3.0, -3.05], None)
    ax = fig.axes[0]
    assert len(ax.lines[-1].get_xdata()) == 3
    assert sorted(t.get_text() for t in ax.texts) == ["×3"]
    assert not ax.patches and ax.get_aspect() == 1.0
    # the tolerance follows the poles' scale: slow poles a factor 2 apart are two markers
    ax = plot_poles([-1e-6, -2e-6], Disk(-1.5e-6, 1e-6)).axes[0]
    assert len(ax.lines[-1].get_xdata()) == 2 and not ax.texts


def test_error_band_legend_is_readable_below_the_panels():
    ts = np.linspace(0, 5, 100)
    truth = np.zeros((100, 3))
    est = {nm: (truth - k, truth, truth + k) for nm, k in (("PO", 1.0), ("FGDO", 0.5), ("FGDO-tuned", 0.3))}
    fig = plot_estimates(ts, truth, est, truth_label="zero error")
    labels, fontsize = _legend_checks(fig, fig.axes)
    assert fontsize >= 10  # Matplotlib's normal size (the legend was 7 pt)
    assert labels == ["zero error"] + [f"{nm}: median and 5–95 % band" for nm in est]
    # what each entry names is drawn in every panel: the truth line, each observer's band and median
    for ax in fig.axes:
        drawn = {a.get_label() for a in ax.lines + ax.collections}
        assert drawn == {"zero error"} | {f"{nm} {w}" for nm in est for w in ("5–95 % band", "median")}
    lowest_axes = min(ax.get_window_extent().y0 for ax in fig.axes)
    leg = fig.legends[0].get_window_extent()
    assert leg.y1 <= lowest_axes and lowest_axes - leg.y1 < 0.15 * fig.bbox.height  # just below


def test_tuning_curve_marks_the_heldout_loss_before_and_after():
    steps = np.arange(1, 11)
    held = np.full(10, np.nan)
    held[4::5] = [2.0, 1.5]
    fig = plot_tuning_curve(steps, 3.0 / steps, held, heldout_before=2.5, heldout_after=1.4)
    ax = fig.axes[0]
    by_label = {ln.get_label(): ln for ln in ax.lines}
    before = next(ln for lab, ln in by_label.items() if lab.startswith("held-out before tuning"))
    after = next(ln for lab, ln in by_label.items() if lab.startswith("held-out after tuning"))
    assert list(before.get_xydata()[0]) == [0.0, 2.5]
    assert list(after.get_xydata()[0]) == [10.0, 1.4]
    assert "(-44.0 %)" in after.get_label()
    # the held-out curve starts at the design before tuning and skips unevaluated steps
    assert by_label["held-out loss"].get_xydata().tolist() == [[0.0, 2.5], [5.0, 2.0], [10.0, 1.5]]
    legend = [t.get_text() for t in ax.get_legend().get_texts()]
    assert set(legend) == {lab for lab in by_label if not lab.startswith("_")}
    y0, y1 = ax.get_ylim()
    assert y0 < 1.4 and 2.5 * 1.01 < y1  # both markers inside the frame


def test_pole_plot_of_a_region_class_fojax_does_not_know():
    # a user's own region (an ellipse): shaded from its margin, named in the legend, equal axes
    from fojax.design import AbstractRegion

    class Ellipse(AbstractRegion):
        def characteristic(self):  # not an LMI region: the plot must not need it
            raise AssertionError("the pole plot asked for the region's LMI characteristic; it must draw "
                                 "a region from its margin alone")

        def margin(self, eigs):
            s = np.asarray(eigs)
            return 1.0 - ((s.real + 3.0) / 2.0) ** 2 - s.imag**2

        def describe(self):
            return "ellipse"

        def tightened(self, fraction):
            return self

        def target(self):
            return -3.0 + 0j

        def to_dict(self):
            return {}

    fig = plot_poles(POLES, Ellipse())
    labels, _ = _legend_checks(fig, fig.axes)
    ax = fig.axes[0]
    assert "region: ellipse" in labels and ax.get_aspect() == 1.0
    [filled, outline] = ax.collections[:2]
    assert filled.get_paths() and outline.get_paths()
    (x0, x1), (y0, y1) = ax.get_xlim(), ax.get_ylim()
    verts = np.concatenate([p.vertices for p in outline.get_paths()])
    assert verts[:, 0].min() > -5.01 and verts[:, 0].max() < -0.99 and np.abs(verts[:, 1]).max() < 1.01
    assert x0 < -5.0 and -1.0 < x1 and y0 < -1.0 and 1.0 < y1  # all of it in view


# ------------------------------------------------------------------ figures for notebooks
# Oracles: Matplotlib's own record of what an Axes holds (its lines, patches, collections),
# the files' signatures as each format's specification fixes them (PNG, PDF, SVG, EPS
# headers), and the folder's listing (no file without `path=`).
from matplotlib.figure import Figure  # noqa: E402


def _plots(ts, eigs):
    truth = np.stack([np.sin(ts)], axis=1)
    return {
        "poles": (plot_poles, (eigs, Disk(-2.0, 1.0)), {"plant_poles": PLANT}),
        "estimates": (plot_estimates, (ts, truth, {"PO": (truth - 0.2, truth, truth + 0.2)}), {}),
        "errors": (plot_error_distributions, ({"PO": np.arange(1.0, 9.0), "FGDO": np.arange(2.0, 10.0)},), {}),
        "tuning": (plot_tuning_curve, (np.arange(5), 1.0 / (1.0 + np.arange(5.0))), {}),
    }


@pytest.mark.parametrize("which", ["poles", "estimates", "errors", "tuning"])
def test_plots_draw_into_the_given_axes_and_write_nothing_without_path(which, tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    plot, args, kw = _plots(np.linspace(0, 5, 50), POLES)[which]
    fig = plot(*args, **kw)  # a new figure, no file
    assert isinstance(fig, Figure) and len(fig.axes) == 1
    mine = Figure(figsize=(9, 4))
    left, right = mine.subplots(1, 2)
    right.plot([0, 1], [0, 1], label="mine")
    out = plot(*args, ax=left, **kw)
    assert out is mine  # the Figure of the given Axes
    assert len(left.lines) + len(left.patches) + len(left.collections) > 0  # drawn into `left` ...
    assert [ln.get_label() for ln in right.lines] == ["mine"] and not right.patches  # ... only
    assert not mine.legends  # its legend on the given Axes, not on the user's figure
    assert tuple(mine.get_size_inches()) == (9.0, 4.0)
    if which == "poles":  # equal axes in the given Axes too
        assert left.get_aspect() == 1.0
    assert list(tmp_path.iterdir()) == []


@pytest.mark.parametrize("suffix, magic", [(".png", b"\x89PNG"), (".pdf", b"%PDF"), (".svg", b"<?xml"),
                                           (".eps", b"%!PS-Adobe")])
def test_plots_write_the_format_of_the_suffix(suffix, magic, tmp_path):
    for which, (plot, args, kw) in _plots(np.linspace(0, 5, 50), POLES).items():
        path = tmp_path / f"{which}{suffix}"
        plot(*args, path=path, **kw)
        assert path.read_bytes().startswith(magic), which
    with pytest.raises(ValueError, match=r"suffix '\.xyz'.*\.png"):
        plot_poles(POLES, path=tmp_path / "poles.xyz")
    assert not (tmp_path / "poles.xyz").exists()


def test_estimates_into_one_axes_per_component_and_bad_axes():
    ts = np.linspace(0, 1, 20)
    truth = np.stack([ts, -ts], axis=1)
    fig = Figure()
    axes = fig.subplots(2, 1)
    assert plot_estimates(ts, truth, {"PO": (truth - 1, truth, truth + 1)}, ax=axes) is fig
    assert all(len(a.lines) == 2 and len(a.collections) == 1 for a in axes)
    with pytest.raises(TypeError, match="2 matplotlib Axes"):
        plot_estimates(ts, truth, {"PO": (truth - 1, truth, truth + 1)}, ax=axes[0])
    with pytest.raises(TypeError, match="a matplotlib Axes"):
        plot_poles(POLES, ax="left")


def test_plots_without_matplotlib_name_the_extra(monkeypatch):
    import sys

    for name in [m for m in sys.modules if m == "matplotlib" or m.startswith("matplotlib.")]:
        monkeypatch.delitem(sys.modules, name)
    monkeypatch.setitem(sys.modules, "matplotlib", None)  # `import matplotlib` raises ImportError
    with pytest.raises(ImportError, match=r"pip install 'fojax\[plot\]'"):
        plot_poles(POLES)


# ---------------------------------------------------------------- files: modes, folder, manifest
# Oracles: the POSIX rule (a new file gets 0o666 & ~umask), pathlib's resolution of where a
# path lands, and hashlib's SHA-256 of the bytes read back.


@pytest.mark.skipif(os.name != "posix", reason="POSIX permission bits")
@pytest.mark.parametrize("umask", [0o022, 0o027, 0o077], ids=["022", "027", "077"])
def test_files_get_the_mode_the_umask_gives(tmp_path, umask):
    # private: the runner's writer is tested itself
    from fojax.studies._runner import _atomic_write

    old = os.umask(umask)
    try:
        folder = new_results_folder(tmp_path, name="run")
        paths = [atomic_write_text(folder / "a.txt", "x"), atomic_write_text(tmp_path / "b.txt", "y")]
        paths.append(atomic_write_text(folder / "a.txt", "z", overwrite=True))  # replaced: same rule
        _atomic_write(str(folder / "c.json"), lambda f: f.write(b"{}"))  # study results, checkpoints
        paths += [folder / "c.json", folder / "fojax-manifest.json"]
    finally:
        os.umask(old)
    for p in paths:
        assert os.stat(p).st_mode & 0o777 == 0o666 & ~umask, p
    assert os.stat(folder).st_mode & 0o777 == 0o777 & ~umask


def test_nothing_is_written_outside_a_results_folder(tmp_path, design):
    # private: the runner's writer is tested itself
    from fojax.studies._runner import _atomic_write

    folder = new_results_folder(tmp_path / "out", name="run")
    elsewhere = tmp_path / "elsewhere"
    elsewhere.mkdir()
    (folder / "link").symlink_to(elsewhere, target_is_directory=True)
    attempts = [
        lambda: atomic_write_text(folder / "../../escaped.txt", "x"),
        lambda: atomic_write_text(folder / "sub" / ".." / ".." / "escaped.txt", "x"),
        lambda: save_design(design, folder / "../escaped.npz"),
        lambda: plot_tuning_curve([0, 1], [2.0, 1.0], path=folder / "../escaped.png"),
        lambda: write_report(folder, title="t", filename="../escaped.md"),
        lambda: write_metrics(folder, {"a": 1.0}, name="../escaped"),
        lambda: _atomic_write(str(folder / "../escaped"), lambda f: f.write(b"x")),
        lambda: atomic_write_text(folder / "link" / "escaped.txt", "x"),  # a symlink out of it
        lambda: atomic_write_text(folder / ".", "x"),
    ]
    for attempt in attempts:
        with pytest.raises(fojax.errors.UnsafePathError, match=r"outside the results folder .*run") as info:
            attempt()
        assert not info.value.resolved.is_relative_to(folder.resolve()) or info.value.resolved == folder.resolve()
    found = sorted(p.relative_to(tmp_path).as_posix() for p in tmp_path.rglob("*"))
    assert found == ["elsewhere", "out", "out/run", "out/run/link"]
    # inside the folder (also through a subfolder) and outside any results folder: fine
    (folder / "sub").mkdir()
    assert atomic_write_text(folder / "sub" / ".." / "in.txt", "x").read_text() == "x"
    assert atomic_write_text(elsewhere / "free.txt", "x").read_text() == "x"
    for bad in ("../x", "a/b", ".hidden", ""):
        with pytest.raises(fojax.errors.InputError, match=r"results folder name \(--name\) .* cannot be used"):
            new_results_folder(tmp_path, name=bad)
    with pytest.raises(fojax.errors.InputError, match="results folder prefix"):
        new_results_folder(tmp_path, prefix="../up")
    assert not (tmp_path / "x").exists() and not (tmp_path.parent / "x").exists()


def test_manifest_lists_every_file_written_with_its_hash(tmp_path, design):
    import hashlib

    folder = new_results_folder(tmp_path)
    written = [
        save_design(design, folder / "obs.npz"),
        plot_tuning_curve([0, 1], [2.0, 1.0], path=folder / "tune.png") and folder / "tune.png",
        *write_metrics(folder, {"a": np.arange(3.0)}),
        write_report(folder, title="t"),
    ]
    (folder / "notes.txt").write_text("mine")  # not written by fojax: not listed
    manifest = json.loads((folder / "fojax-manifest.json").read_text())
    assert manifest["format"] == "fojax-manifest"
    assert sorted(manifest["files"]) == sorted(p.name for p in written)
    for p in written:
        data = p.read_bytes()
        assert manifest["files"][p.name] == {"sha256": hashlib.sha256(data).hexdigest(), "bytes": len(data)}


def test_overwrite_replaces_the_previous_run_and_keeps_the_users_files(tmp_path):
    folder = new_results_folder(tmp_path, name="run")
    for n in ("a.txt", "b.txt", "c.txt"):
        atomic_write_text(folder / n, f"first {n}")
    (folder / "notes.txt").write_text("my notes")  # the user's
    (folder / "c.txt").write_text("edited by the user")  # changed since fojax wrote it
    assert new_results_folder(tmp_path, name="run", overwrite=True) == folder
    # the previous run's unchanged files are gone; the user's notes and edit stay
    assert sorted(p.name for p in folder.iterdir()) == ["c.txt", "fojax-manifest.json", "notes.txt"]
    assert json.loads((folder / "fojax-manifest.json").read_text())["files"] == {}  # before any new write
    atomic_write_text(folder / "a.txt", "second a")
    manifest = json.loads((folder / "fojax-manifest.json").read_text())
    assert list(manifest["files"]) == ["a.txt"]
    assert manifest["replaced_previous_run"] == {"removed": ["a.txt", "b.txt"], "kept_changed": ["c.txt"]}
    assert (folder / "notes.txt").read_text() == "my notes"
    assert (folder / "c.txt").read_text() == "edited by the user"
    # a manifest edited to point outside the folder never deletes there
    outside = tmp_path / "precious.txt"
    outside.write_text("keep")
    m = json.loads((folder / "fojax-manifest.json").read_text())
    m["files"]["../precious.txt"] = {"sha256": "x", "bytes": 4}
    m["files"][str(outside)] = {"sha256": "x", "bytes": 4}
    (folder / "fojax-manifest.json").write_text(json.dumps(m))
    new_results_folder(tmp_path, name="run", overwrite=True)
    assert outside.read_text() == "keep" and not (folder / "a.txt").exists()


def test_load_design_of_a_config_file_says_what_it_is(tmp_path):
    from fojax.config import example_path

    for path, what in [
        (example_path("example_4_1_3"), r"is not a fojax design file: it is a text file \(a TOML config\?\)"),
        (tmp_path / "a.npy", r"it is a single NumPy array \(\.npy\)"),
        (tmp_path / "junk.npz", r"it is a binary file that is not a \.npz archive"),
        (tmp_path / "empty.npz", r"it is empty"),
        (tmp_path / "truncated.npz", r"not a readable fojax design file .*damaged or truncated"),
    ]:
        np.save(tmp_path / "a.npy", np.zeros(2))
        (tmp_path / "junk.npz").write_bytes(b"\x00\xff" * 10)
        (tmp_path / "empty.npz").write_bytes(b"")
        (tmp_path / "truncated.npz").write_bytes(b"PK\x03\x04" + b"\x00" * 10)
        for fn in (load_design, read_design_metadata):
            with pytest.raises(fojax.errors.InputError, match=what) as info:
                fn(path)
            assert "load_design reads the .npz files written by fojax.results.save_design or `fojax design`" in str(info.value)


def test_a_continued_run_keeps_the_manifest_of_the_first(tmp_path):
    # private: the manifest writer is tested itself
    from fojax._io import register_results_folder

    folder = new_results_folder(tmp_path, name="run")
    atomic_write_text(folder / "a.txt", "first")
    register_results_folder(folder, continue_run=True)  # as `fojax study --resume` does
    atomic_write_text(folder / "b.txt", "second")
    with pytest.raises(fojax.errors.UnsafePathError):
        atomic_write_text(folder / ".." / "c.txt", "x")
    manifest = json.loads((folder / "fojax-manifest.json").read_text())
    assert sorted(manifest["files"]) == ["a.txt", "b.txt"] and len(manifest["continued"]) == 1


# ==================================================================================================
# save_design / load_design for every design class of fojax.design: Takagi–Sugeno, unknown-input,
# finite-time and fault-estimator designs round-trip bit-exactly (every array, every number of the
# report), load as the same class, and their observers give identical vector fields and outputs;
# foreign membership classes are never imported.
# ==================================================================================================


KINDS = ("ts", "uio", "finite_time", "fault")
CLASSES = {
    "ts": TakagiSugenoObserverDesign,
    "uio": UnknownInputObserverDesign,
    "finite_time": FiniteTimeObserverDesign,
    "fault": FaultEstimatorDesign,
}


@pytest.fixture(scope="module")
def designs():
    """One small thesis design of every kind (each LMI solved once per module)."""
    arm = fojax.models.robot_arm_ts().system
    ex413 = fojax.models.example_4_1_3()
    E, A, B, C, L = (np.asarray(x) for x in (ex413.E, ex413.A, ex413.B, ex413.C, ex413.L))
    closed = fojax.DescriptorSystem(E, A + B @ L, B, C)
    ex312 = fojax.models.example_3_1_2()
    ex337 = fojax.models.example_3_3_7()
    sys337 = fojax.DescriptorSystem(ex337.E, ex337.A, ex337.B, ex337.C)
    return {
        # z = [x2, x4] of the robot arm (x5 is refused by the T-S observer, see test_takagi_sugeno)
        "ts": design_ts_observer(arm, np.eye(5)[[1, 3]], kind="generalized"),
        "uio": design_unknown_input_observer(closed, np.eye(4)[:, [2]], L),
        "finite_time": design_finite_time_observer(
            ex312.system, ex312.L, h=0.5, regions=((-5, 0.5), (-2, 0.5))
        ),
        "fault": design_fault_estimator(
            sys337, ex337.L, Fa=ex337.Fa, Fs=ex337.Fs, kind="generalized", region=Disk(-2.0, 1.0)
        ),
    }


@pytest.fixture(scope="module")
def saved(designs, tmp_path_factory):
    """Every design saved and loaded back once: ``{kind: (path, loaded)}``."""
    tmp = tmp_path_factory.mktemp("kinds")
    out = {}
    for k, d in designs.items():
        path = save_design(d, tmp / f"{k}.npz", metadata={"case": k})
        out[k] = (path, load_design(path))
    return out


@pytest.mark.parametrize("kind", KINDS)
def test_round_trip_same_class_bit_identical(designs, saved, kind):
    d, (path, loaded) = designs[kind], saved[kind]
    assert type(loaded) is CLASSES[kind]
    n = assert_designs_identical(d, loaded)
    # every matrix was compared (observer, structure, params, T, K, Z_eff, X, eigenvalues, ...)
    assert n >= {"ts": 30, "uio": 35, "finite_time": 60, "fault": 35}[kind], n
    assert str(loaded.report if kind != "finite_time" else loaded) == str(
        d.report if kind != "finite_time" else d
    )
    meta = read_design_metadata(path)
    assert meta["format_version"] == 3 and meta["design_class"] == CLASSES[kind].__name__
    assert meta["user"] == {"case": kind} and meta["fojax_version"] == fojax.__version__
    # the file holds plain arrays only (no pickled objects)
    with zipfile.ZipFile(path) as z, np.load(path, allow_pickle=False) as data:
        assert all(n.endswith(".npy") for n in z.namelist())
        assert all(data[k].dtype != object for k in data.files)


def _node(meta, *path):
    """The skeleton node of a saved design at a field path (format 3: ``meta["tree"]``)."""
    node = meta["tree"]
    for p in path:
        node = node["items"][p] if isinstance(p, int) else node["fields"][p]
    return node


def test_metadata_per_class(designs, saved):
    ts = read_design_metadata(saved["ts"][0])
    assert ts["summary"]["kind"] == "generalized" and _node(ts, "observer", "membership")["class"] == (
        "fojax.plant._takagi_sugeno:SectorMembership")
    assert ts["summary"]["report"]["extra"]["lyapunov_max_eig"] == designs["ts"].report.extra["lyapunov_max_eig"]
    assert _node(ts, "structure", "A")["shape"] == [2, 5, 5]  # two rules
    uio = read_design_metadata(saved["uio"][0])
    assert uio["summary"]["sizes"] == {"n": 4, "m": 2, "p": 3, "q": 2, "q0": designs["uio"].structure.q0}
    assert _node(uio, "D")["shape"] == [4, 1]
    ft = read_design_metadata(saved["finite_time"][0])
    assert _node(ft, "h") == {"$": "float", "repr": "0.5"}
    assert [_node(ft, "designs", i, "region")["class"] for i in (0, 1)] == ["fojax.design._regions:Disk"] * 2
    fault = read_design_metadata(saved["fault"][0])
    assert (_node(fault, "q"), _node(fault, "n_faults"), _node(fault, "ramp")) == (2, 3, False)
    assert _node(fault, "design", "structure", "E")["shape"] == [9, 9]  # 6 states + 3 constant faults
    # what the inner designs of a loaded object carry
    loaded_ft = saved["finite_time"][1]
    assert all(di.solver["saved"]["user"] == {"case": "finite_time"} for di in loaded_ft.designs)
    assert saved["uio"][1].solver["saved"]["user"] == {"case": "uio"}


def _random_inputs(obs, m, p, seed):
    rng = np.random.default_rng(seed)
    xi = jnp.asarray(rng.normal(size=obs.state_size))
    return xi, jnp.asarray(rng.normal(size=m)), jnp.asarray(3.0 * rng.normal(size=p))


@pytest.mark.parametrize("kind", KINDS)
def test_loaded_observer_gives_identical_vector_field_and_output(designs, saved, kind):
    d, loaded = designs[kind], saved[kind][1]
    o1, o2 = d.observer, loaded.observer
    s = (d.designs[0] if kind == "finite_time" else d.design if kind == "fault" else d).structure
    for seed in range(4):  # y of size 3: the T-S weights cover both clipped ends and the inside
        xi, u, y = _random_inputs(o1, s.m, s.p, seed)
        f1, f2 = o1.vector_field(0.0, xi, u, y), o2.vector_field(0.0, xi, u, y)
        assert np.array_equal(f1, f2) and np.all(np.isfinite(f1))
        assert np.array_equal(o1.output(0.0, xi, u, y), o2.output(0.0, xi, u, y))
    if kind == "ts":
        ys = jnp.asarray([[0.0, 0.0], [0.0, 1.0], [0.0, 4.0], [0.0, -2.5]])
        w1 = jax.vmap(lambda y: o1.weights(jnp.zeros(1), y))(ys)
        assert np.array_equal(w1, jax.vmap(lambda y: o2.weights(jnp.zeros(1), y))(ys))
        assert np.unique(np.round(np.asarray(w1[:, 0]), 12)).size == 4  # the weights vary
    if kind == "finite_time":
        xi2 = _random_inputs(o1, s.m, s.p, 9)[0]
        assert np.array_equal(o1.reconstruct(xi, xi2, u, y), o2.reconstruct(xi, xi2, u, y))


class _ForeignMembership(fojax.plant.AbstractMembership):
    """Two rules, w1 = logistic(a * y0), and a Python callable: not storable in a file."""

    a: jax.Array
    squash: object = eqx.field(static=True)

    @property
    def num_rules(self):
        return 2

    def __call__(self, y, u):
        w1 = self.squash(self.a * y[0])
        return jnp.stack([w1, 1.0 - w1])


class _ForeignArraysOnly(fojax.plant.AbstractMembership):
    a: jax.Array

    @property
    def num_rules(self):
        return 2

    def __call__(self, y, u):
        w1 = jax.nn.sigmoid(self.a * y[0])
        return jnp.stack([w1, 1.0 - w1])


def test_foreign_membership_is_never_imported_and_can_be_passed(designs, tmp_path):
    d = designs["ts"]
    custom = _ForeignMembership(jnp.asarray(0.7), jax.nn.sigmoid)
    d2 = dataclasses.replace(d, observer=eqx.tree_at(lambda o: o.membership, d.observer, custom))
    path = save_design(d2, tmp_path / "custom.npz")
    meta = _node(read_design_metadata(path), "observer", "membership")
    assert meta["$"] == "unstored" and meta["reason"].startswith("_ForeignMembership.squash is a ")
    with pytest.raises(fojax.errors.InputError, match=r"cannot be rebuilt: it was not stored.*membership=plant\.membership"):
        load_design(path)
    loaded = load_design(path, membership=custom)
    assert_designs_identical(d2, loaded)
    # a tree of arrays is stored, but its class is outside fojax: never imported from a file
    arrays_only = _ForeignArraysOnly(jnp.asarray(0.7))
    d3 = dataclasses.replace(d, observer=eqx.tree_at(lambda o: o.membership, d.observer, arrays_only))
    path3 = save_design(d3, tmp_path / "arrays.npz")
    assert _node(read_design_metadata(path3), "observer", "membership", "a")["$"] == "array"
    with pytest.raises(fojax.errors.InputError, match=r"_ForeignArraysOnly is not a fojax class \(fojax never imports"):
        load_design(path3)
    xi, u, y = _random_inputs(d3.observer, 1, 2, 0)
    o = load_design(path3, membership=arrays_only).observer
    assert np.array_equal(o.vector_field(0.0, xi, u, y), d3.observer.vector_field(0.0, xi, u, y))


def test_format_1_files_load_and_membership_argument_is_ts_only(designs, tmp_path):
    """Format 1 = format 2 without ``design_class`` (functional designs only): made from the
    committed format-2 file written by fojax before format 3 (tests/data/designs_v2)."""
    v2 = pathlib.Path(__file__).parent / "data" / "designs_v2" / "functional.npz"
    with np.load(v2, allow_pickle=False) as data:
        arrays = {k: data[k] for k in data.files}
    meta = json.loads(str(arrays["__metadata__"][()]))
    assert meta.pop("design_class") == "FunctionalObserverDesign" and meta["format_version"] == 2
    meta["format_version"] = 1
    arrays["__metadata__"] = np.array(json.dumps(meta))
    np.savez(tmp_path / "v1.npz", **arrays)
    old = load_design(tmp_path / "v1.npz")
    assert type(old) is FunctionalObserverDesign
    assert_designs_identical(load_design(v2), old)
    with pytest.raises(fojax.errors.InputError, match="membership= applies to Takagi–Sugeno designs only"):
        load_design(v2, membership=designs["ts"].observer.membership)
    with pytest.raises(fojax.errors.InputError, match="membership= applies to Takagi–Sugeno designs only"):
        load_design(save_design(designs["uio"], tmp_path / "uio.npz"), membership=designs["ts"].observer.membership)
    meta["format_version"], meta["design_class"] = 2, "FancyDesign"
    arrays["__metadata__"] = np.array(json.dumps(meta))
    np.savez(tmp_path / "fancy.npz", **arrays)
    with pytest.raises(fojax.errors.InputError, match="class 'FancyDesign', which this fojax version cannot load"):
        load_design(tmp_path / "fancy.npz")
