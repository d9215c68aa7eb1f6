"""The figures: the verification figure beside each passport (before and after compensation on scales of their
own, one panel per visit of a temperature, points beyond their limit circled) and the constants against
temperature with the fitted model and its residuals."""

from __future__ import annotations

import numpy as np
import pytest
from PIL import Image

from pipeline import plots
from pipeline.verify import VerificationRow


def _row(
    temp_c: float, position: str, dg_ug: float, tol_ug: float = 1000.0, t: int = 0, after_ug: float | None = None
) -> VerificationRow:
    after = 0.1 * dg_ug if after_ug is None else after_ug
    return VerificationRow(
        temp_c=temp_c,
        position=position,
        run_id="r",
        t_start_ns=t,
        t_end_ns=t + 1,
        dg_uncompensated_g=dg_ug * 1e-6,
        dg_method1_g=after * 1e-6,
        dg_method2_g=2 * after * 1e-6,
        dg_method2_simplified_g=0.0,
        tolerance_g=tol_ug * 1e-6,
        passed=abs(after) <= tol_ug,
    )


def _timed(rows):
    return [VerificationRow(**{**r.to_dict(), "t_start_ns": k, "t_end_ns": k + 1}) for k, r in enumerate(rows)]


def test_panels_per_visit_coldest_first():
    """Rows in time order (+45, then -10, then one VP at +70, then +44.6 again) give four panels: -10, +45 visit 1,
    +45 visit 2 (44.6 C, after the +70 visit), +70; each at least four slots wide with its points centred, one empty
    slot between panels; dicts (a passport's rows) give the same panels."""
    rows = _timed(
        [_row(45.0, f"VP{k}", 100.0 * k) for k in range(1, 7)]
        + [_row(-10.0, f"VP{k}", -50.0) for k in (1, 2)]
        + [_row(70.2, "VP6", 3.0)]
        + [_row(44.6, "VP1", 7.0)]
    )
    panels = plots._panels([r.to_dict() for r in rows])
    assert [round(p["temp_c"], 1) for p in panels] == [-10.0, 45.0, 44.6, 70.2]
    assert [(p["visit"], p["visits"]) for p in panels] == [(1, 1), (1, 2), (2, 2), (1, 1)]
    assert [[r["position"] for r in p["rows"]] for p in panels] == [
        ["VP1", "VP2"],
        [f"VP{k}" for k in range(1, 7)],
        ["VP1"],
        ["VP6"],
    ]
    assert [p["width"] for p in panels] == [4, 6, 4, 4]
    assert [p["x0"] for p in panels] == [0.0, 5.0, 12.0, 17.0]
    np.testing.assert_allclose(panels[0]["x"], [1.5, 2.5])  # two points centred in four slots
    np.testing.assert_allclose(panels[3]["x"], [19.0])
    for p in panels:
        assert p["x0"] < p["x"].min() and p["x"].max() < p["x0"] + p["width"]
    assert plots._panels([]) == []


def _red_rings(img: np.ndarray) -> np.ndarray:
    return np.all(np.abs(img.astype(int) - [255, 0, 0]) < 40, axis=-1)


def test_before_and_after_on_their_own_scales_fails_circled(tmp_path):
    rows = _timed(
        [
            _row(t, f"VP{k}", 500.0 * (k - 3), tol)
            for t, tol in ((-10.0, 1000.0), (20.0, 300.0), (45.0, 1000.0))
            for k in range(1, 7)
        ]
    )
    path = plots.plot_verification(rows, tmp_path / "sub" / "v0001.png", title="AU-0001 v1")
    img = np.asarray(Image.open(path).convert("RGB"))
    slots = 3 * 6 + 2
    width_in = plots._MARGINS_IN["left"] + plots._MARGINS_IN["right"] + plots._SLOT_IN * slots
    assert img.shape[:2] == (
        round(plots._HEIGHT_IN * plots._VERIFICATION_DPI),
        round(width_in * plots._VERIFICATION_DPI),
    )
    h = img.shape[0]
    upper, lower = img[: h // 2], img[h // 2 :]
    blue = np.all(np.abs(img.astype(int) - [0x1F, 0x77, 0xB4]) < 30, axis=-1)  # uncompensated (C0): above only
    orange = np.all(np.abs(img.astype(int) - [0xFF, 0x7F, 0x0E]) < 30, axis=-1)  # method 1 (C1): below only
    assert blue[: h // 2].sum() > 500 and blue[h // 2 :].sum() < 50
    assert orange[h // 2 :].sum() > 500 and orange[: h // 2].sum() < 50
    # before: 1500 ug at VP6 -10/+45 and > 300 ug at +20 are beyond their limits: rings above, none below
    assert _red_rings(upper).sum() > 200 and _red_rings(lower).sum() == 0
    # after (method 1 up to 150 ug): the lower axes have their own scale, so its points are not flat on zero
    ys = np.flatnonzero(orange[h // 2 :].any(axis=1))
    assert ys.max() - ys.min() > 0.3 * plots._PANEL_IN * plots._VERIFICATION_DPI
    # one failing compensated row: ringed below
    bad = rows[:6] + [VerificationRow(**{**rows[6].to_dict(), "dg_method1_g": 400e-6, "passed": False})]
    img2 = np.asarray(Image.open(plots.plot_verification(bad, tmp_path / "bad.png")).convert("RGB"))
    assert _red_rings(img2[img2.shape[0] // 2 :]).sum() > 50
    empty = plots.plot_verification([], tmp_path / "empty.png")
    assert Image.open(empty).size[0] == round(
        (plots._MARGINS_IN["left"] + plots._MARGINS_IN["right"] + plots._SLOT_IN * plots._MIN_SLOTS)
        * plots._VERIFICATION_DPI
    )


def _labels_alike(fig, canvas, again: np.ndarray, fresh: np.ndarray, k: int, axis_labels: bool = False) -> np.ndarray:
    """Where the fresh figure ``fig`` (drawn on ``canvas``) has y tick labels in view (and, with ``axis_labels``,
    y axis labels): pasted as pixels within 1/4 pixel of matplotlib's place in ``again``, so their antialiased edges
    may differ from ``fresh``'s, not their ink (a label 1 pixel off fails). The mask of those labels' boxes."""
    h = fresh.shape[0]
    labels = np.zeros(fresh.shape[:2], bool)
    for ax in fig.axes:
        lo, hi = sorted(ax.get_ylim())
        slack = 1e-9 * (hi - lo)  # a tick drawn at a limit it misses by a rounding error
        texts = [t for t in ax.yaxis.get_majorticklabels() if lo - slack <= t.get_position()[1] <= hi + slack]
        for text in texts + ([ax.yaxis.label] if axis_labels and ax.get_ylabel() else []):
            box = text.get_window_extent(canvas.get_renderer()).padded(2)
            rows, cols = slice(int(h - box.y1), int(np.ceil(h - box.y0))), slice(int(box.x0), int(np.ceil(box.x1)))
            labels[rows, cols] = True
            ink_again, ink_fresh = (255 - im[rows, cols, :3].astype(int) for im in (again, fresh))
            assert abs(ink_again.sum() - ink_fresh.sum()) < 0.05 * ink_fresh.sum(), (k, text.get_text())
            assert np.abs(ink_again - ink_fresh).max() < 128, (k, text.get_text())
    return labels


def test_verification_figure_drawn_again_is_the_figure_made_afresh(tmp_path):
    """plot_verification fills the figure of its previous call again when the panels are the same (its fixed
    artists and its legends kept as pixels): each PNG is the one of a figure made afresh for those rows alone,
    whatever was drawn before (other errors and scales, rings above or below or none, another layout, no rows),
    but for a few pixels of a legend where a frame is drawn over it (a legend's ring touches the upper axes) and the
    edges of the y tick and axis labels (pasted as pixels within 1/4 pixel of their place, the axis labels where
    matplotlib puts them: left of the tick labels)."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg

    layout = [(t, tol) for t, tol in ((-10.0, 1000.0), (20.0, 300.0), (45.0, 1000.0))]
    first = _timed([_row(t, f"VP{k}", 500.0 * (k - 3), tol) for t, tol in layout for k in range(1, 7)])
    calm = _timed([_row(t, f"VP{k}", 20.0 * k, tol, after_ug=-0.5 * k) for t, tol in layout for k in range(1, 7)])
    failed = [
        VerificationRow(**{**r.to_dict(), "dg_method2_g": 2e-3 if k == 4 else r.dg_method2_g})
        for k, r in enumerate(calm)
    ]
    other = first[:7]
    for k, rows in enumerate([first, calm, failed, other, [], first, failed]):
        again = plots.plot_verification(rows, tmp_path / f"again{k}.png", title=f"t{k}")
        panels = plots._panels([r.to_dict() for r in rows])
        fresh = plots._VerificationFrame(panels)
        fresh.fill(panels, f"t{k}")
        for ax, legend in zip((fresh.before, fresh.after), [legend for _, legend in fresh.shown]):
            ax.add_artist(legend)  # drawn whole, as matplotlib draws a legend of its axes
        canvas = FigureCanvasAgg(fresh.fig)
        canvas.print_png(tmp_path / f"fresh{k}.png", pil_kwargs={"compress_level": 1})
        a, f = (np.asarray(Image.open(p)) for p in (again, tmp_path / f"fresh{k}.png"))
        assert a.shape == f.shape and len(fresh.shown) == (2 if rows else 0)
        under = np.zeros(f.shape[:2], bool)
        for _, legend in fresh.shown:
            box = legend.get_window_extent(canvas.get_renderer()).padded(2)
            under[int(f.shape[0] - box.y1) : int(np.ceil(f.shape[0] - box.y0)), int(box.x0) : int(np.ceil(box.x1))] = 1
        labels = _labels_alike(fresh.fig, canvas, a, f, k, axis_labels=True)
        assert labels.sum() > (1000 if rows else 0)
        differ = np.any(a != f, axis=-1)
        assert not (differ & ~under & ~labels).any(), (k, np.argwhere(differ & ~under & ~labels)[:5])
        assert (differ & ~labels).sum() <= 10, k
    assert _red_rings(np.asarray(Image.open(tmp_path / "again2.png").convert("RGB"))[280:]).sum() > 50


def test_constant_changes_in_engineering_units():
    K0 = np.diag([0.5, -0.55, 0.6])
    K0[0, 1] = 1e-3
    U00 = np.array([0.01, 0.0, -0.02])
    K = K0[None].copy()
    K[0, 0, 0] *= 1 + 200e-6  # +200 ppm of the x gain
    K[0, 1, 2] += -0.55 * 50e-6  # yz: +50 ppm of the y gain (the change over K_yy, sign included)
    U0 = (U00 + np.array([0.5 * 30e-6, 0.0, 0.0]))[None]  # +30 micro-g on x
    ch = plots.constant_changes(K, U0, K0, U00)
    np.testing.assert_allclose(ch["gain"][0], [200.0, 0.0, 0.0], atol=1e-9)
    np.testing.assert_allclose(ch["cross"][0, 1], [0.0, 50.0], atol=1e-9)  # row y: (yx, yz) over K_yy
    np.testing.assert_allclose(ch["offset"][0], [30.0, 0.0, 0.0], atol=1e-9)


def _constants_passport(
    slope: float = 1e-5, off_v: float = 5e-6, temps=(-40.0, -10.0, 20.0, 45.0, 70.0), curve: float = 3e-8
) -> dict:
    """A passport document with per-plateau constants on a quadratic (gain ``slope`` per C, ``curve`` per C^2),
    their uncertainties and model; the fourth plateau's x offset ``off_v`` off the model (5e-6 V: ~9 micro-g)."""
    from pipeline.thermal import fit_thermal_model

    temps = np.asarray(temps)
    K0 = np.diag([0.55, 0.548, 0.548])
    K = np.array([K0 * (1 + slope * (t - 20) + curve * (t - 20) ** 2) for t in temps])
    U0 = np.array([[1e-3 + 2e-5 * (t - 20), 5e-4, 4e-4] for t in temps])
    U0[3, 0] += off_v
    model = fit_thermal_model(temps, K, U0, "poly2", 20.0, 3.0)
    sigma_K, sigma_U0 = np.full((3, 3), 2e-7), np.full(3, 1e-7)
    return {
        "coefficients": {"K": np.asarray(model.K0).tolist(), "U0": np.asarray(model.U00).tolist()},
        "normal_temp_c": 20.0,
        "thermal_model": model.to_dict(),
        "per_plateau": [{"temp_c": t, "K": k.tolist(), "U0": u.tolist()} for t, k, u in zip(temps, K, U0)],
        "uncertainty": {"per_plateau": [{"K": sigma_K.tolist(), "U0": sigma_U0.tolist()} for _ in temps]},
    }


def test_constants_figure_points_model_and_residuals(tmp_path):
    """A passport's per-plateau constants, its model and uncertainties drawn: 18 axes (gain, cross-axis, offset and
    their residuals, per axis); a plateau that departs from the model shows in its residual panel."""
    passport = _constants_passport()
    path = plots.plot_constants(passport, tmp_path / "c.png", title="AU-0001 v1")
    img = np.asarray(Image.open(path).convert("RGB"))
    assert img.shape[0] > 800 and img.shape[1] > 1000
    blue = np.all(np.abs(img.astype(int) - [0x1F, 0x77, 0xB4]) < 30, axis=-1)
    assert blue.sum() > 3000
    alone = plots.plot_constants({**passport, "per_plateau": [], "valid_temp_c": [-40.0, 70.0]}, tmp_path / "m.png")
    img = np.asarray(Image.open(alone).convert("RGB"))  # a differential passport: its model curves alone
    assert np.all(np.abs(img.astype(int) - [0x1F, 0x77, 0xB4]) < 30, axis=-1).sum() > 1000
    empty = plots.plot_constants({**passport, "per_plateau": []}, tmp_path / "e.png")
    assert Image.open(empty).size == Image.open(path).size
    # every y axis says its unit, the residual rows too
    labels = [ax.get_ylabel() for ax in plots.constants_figure(passport).axes if ax.get_ylabel()]
    assert labels == [
        "gain K_ii\nchange [ppm]",
        "residual\n[ppm]",
        "cross-axis K_ij\nchange [ppm of K_ii]",
        "residual\n[ppm of K_ii]",
        "offset U0_i\nchange [micro-g]",
        "residual\n[micro-g]",
    ]


def test_constants_figure_drawn_again_is_the_figure_made_afresh(tmp_path):
    """plot_constants fills one figure per thread again for each passport, its fixed artists kept as pixels, its
    legends pasted where matplotlib's "best" puts them, its temperature axes pasted per limits and its tick labels
    pasted as pixels: each PNG is the one of a figure made afresh for that passport alone and drawn whole, whatever
    was drawn before (nothing: the warm-up; other values and plateaus, no uncertainties, the model alone, gains
    changing by micro-ppm: a y axis with an offset text), except under the legends (a grid line or a curve through
    a legend is drawn over it, not under) and at the edges of the y tick labels (pasted within 1/4 pixel of their
    place): no pixel differs outside the fresh figure's legends and y tick labels, few under the legends, and each
    tick label has the ink of the fresh one, at most a fraction of a pixel's edge off."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg

    plots.warm_up()  # as a figure worker starts: the frame drawn once empty
    base = _constants_passport()
    others = [
        _constants_passport(slope=-3e-5, off_v=-2e-5, temps=(-30.0, 0.0, 25.0, 45.0, 70.0, 85.0)),
        {**base, "uncertainty": None},
        {**base, "per_plateau": [], "valid_temp_c": [-40.0, 70.0]},
        _constants_passport(slope=4e-5, off_v=0.0, temps=(-40.0, -5.0, 20.0, 70.0)),
        {**_constants_passport(slope=1e-12, curve=0.0), "uncertainty": None},
        base,
    ]
    for k, passport in enumerate(others):
        again = np.asarray(Image.open(plots.plot_constants(passport, tmp_path / f"again{k}.png", title=f"t{k}")))
        fig = plots.constants_figure(passport, title=f"t{k}")
        canvas = FigureCanvasAgg(fig)
        canvas.print_png(tmp_path / f"fresh{k}.png", pil_kwargs={"compress_level": 1})
        fresh = np.asarray(Image.open(tmp_path / f"fresh{k}.png"))
        assert again.shape == fresh.shape
        under = np.zeros(fresh.shape[:2], bool)  # the fresh figure's legends, in pixel rows from the top
        legends = [ax.get_legend() for ax in fig.axes if ax.get_legend() is not None]
        assert len(legends) == 4
        h = fresh.shape[0]
        for legend in legends:
            box = legend.get_window_extent(canvas.get_renderer()).padded(2)
            under[int(h - box.y1) : int(np.ceil(h - box.y0)), int(box.x0) : int(np.ceil(box.x1))] = True
        labels = _labels_alike(fig, canvas, again, fresh, k)
        assert labels.sum() > 1000
        differ = np.any(again != fresh, axis=-1)
        assert not (differ & ~under & ~labels).any(), (k, np.argwhere(differ & ~under & ~labels)[:5])
        assert (differ & under & ~labels).sum() < 0.1 * under.sum(), k


def test_verification_axes_in_milli_g_for_large_errors_and_infinite_errors_left_out(tmp_path):
    """A consumer part's errors before compensation (~5e5 micro-g) are drawn in milli-g, so the axis label stays on
    the figure (in micro-g, 7-character tick labels pushed it off the left edge); an infinite error is left out
    (before: the figure raised "Axis limits cannot be NaN or Inf"); the next unit in micro-g is labelled so again."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg

    layout = [(-10.0, 100.0), (20.0, 100.0), (45.0, 100.0)]
    big = _timed(
        [_row(t, f"VP{k}", 1.5e5 * (k - 3.5), tol, after_ug=300.0 * k) for t, tol in layout for k in range(1, 7)]
    )
    plots.plot_verification(big, tmp_path / "big.png")
    frame = plots._FRAMES.verification
    renderer = FigureCanvasAgg(frame.fig).get_renderer()
    assert frame.before.get_ylabel() == "before: dg  [milli-g]"
    assert frame.after.get_ylabel() == "after: dg  [micro-g]"
    assert frame.before.get_ylim()[1] == pytest.approx(375.0 * 1.15)
    for ax in (frame.before, frame.after):
        assert ax.yaxis.label.get_window_extent(renderer).x0 >= 0
    rings = frame.series[0][3].get_ydata()  # every error before is beyond its 100-micro-g limit: ringed, in milli-g
    np.testing.assert_allclose(np.abs(rings), np.abs([0.15 * (k - 3.5) * 1e3 for _ in layout for k in range(1, 7)]))
    infinite = [
        VerificationRow(**{**r.to_dict(), "dg_uncompensated_g": np.inf}) if k == 2 else r for k, r in enumerate(big)
    ]
    path = plots.plot_verification(infinite, tmp_path / "inf.png")
    assert Image.open(path).size[0] > 0 and np.isnan(frame.series[0][2].get_ydata()[2])
    calm = _timed([_row(t, f"VP{k}", 20.0 * k, tol) for t, tol in layout for k in range(1, 7)])
    plots.plot_verification(calm, tmp_path / "calm.png")
    assert plots._FRAMES.verification.before.get_ylabel() == "before: dg  [micro-g]"
    assert plots._dg_unit(8000.0) == ("micro-g", 1.0) and plots._dg_unit(9000.0) == ("milli-g", 1e3)
    assert plots._dg_unit(2e7) == ("g", 1e6)
