"""Figures (PNG). matplotlib is imported lazily, so the library imports without it; figures are made as
``matplotlib.figure.Figure`` objects (no pyplot state), so they can be drawn from several threads at once."""

from __future__ import annotations

import io
import threading
from pathlib import Path
from typing import TYPE_CHECKING, BinaryIO, Literal

import numpy as np

if TYPE_CHECKING:
    from pipeline.passport.document import Passport

#: The series of the verification figure: row field (g), legend label, matplotlib format, colour; the first on
#: the upper axes (before compensation), the others on the lower axes (after).
_DG_SERIES = (
    ("dg_uncompensated_g", "uncompensated", "o-", "C0"),
    ("dg_method1_g", "method 1 (verdict)", "s-", "C1"),
    ("dg_method2_g", "method 2", "^--", "C2"),
)
#: Width of one verification position on the x axis of the figure (in), and the margins around the axes (in):
#: fixed, so no layout pass (``tight_layout`` measured every text once more: 40 % of the figure's time).
_SLOT_IN = 0.42
_MARGINS_IN = {"left": 0.85, "right": 0.15, "bottom": 0.35, "top": 0.95}
_PANEL_IN = 2.0  # height of each of the two axes (before, after)
_GAP_IN = 0.3  # between them: the legend of the lower axes
_HEIGHT_IN = _MARGINS_IN["top"] + _MARGINS_IN["bottom"] + 2 * _PANEL_IN + _GAP_IN
_VERIFICATION_DPI = 100
#: Fewest slots of a panel (its title needs them) and of the whole axes.
_MIN_PANEL_SLOTS = 4
_MIN_SLOTS = 12


def new_figure(nrows: int, ncols: int, **subplots_kw):
    """A figure of its own (not registered with pyplot) and its axes grid, for writing a PNG with ``savefig``."""
    from matplotlib.figure import Figure

    fig = Figure(figsize=subplots_kw.pop("figsize", None))
    return fig, fig.subplots(nrows, ncols, **subplots_kw)


def plot_verification(rows, path: str | Path, *, title: str = "") -> Path:
    """VP gravity-module errors before and after compensation (like seed 000's Fig. 6-7), in micro-g (milli-g or g
    on an axes whose errors reach 10^4 micro-g or 10^7: :func:`_dg_unit`; an infinite error is not drawn), in two
    axes with scales of their own: above, uncompensated (the normal-temperature constants at every temperature);
    below, compensated by method 1 (the verdict) and method 2. ``rows``: :class:`pipeline.verify.VerificationRow` or
    their dicts (a passport's ``verification``).

    One panel per visit of a verification temperature, coldest first (a temperature visited twice has two panels,
    told apart by "visit 1/2" in their titles), each titled with its temperature and limit, with the limit band
    shaded where it fits the scale; points beyond their limit are circled in red (on the lower axes they failed
    the calibration).

    Drawn for throughput (a fleet draws one per unit): fixed margins (no layout pass), the position names as plain
    texts (no tick objects), legends at fixed places, and the figure of the previous call of this thread filled
    again when its panels are the same (:class:`_VerificationFrame`: the units of one run), its fixed artists kept
    as pixels (:class:`_Layers`).
    """
    panels = _panels([_row_dict(r) for r in rows])
    key = _VerificationFrame.key(panels)
    frame = getattr(_FRAMES, "verification", None)
    if frame is None or frame.layout != key:
        frame = _FRAMES.verification = _VerificationFrame(panels)
    frame.fill(panels, title or "Gravity-module error dg = |a| - 1 at the verification positions")
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    frame.layers.save(path, pasted=tuple(frame.shown))
    return path


class _VerificationFrame:
    """The verification figure of one layout of panels (:meth:`key`: their places, titles and position names),
    with its axes, texts, separators, limit bands and lines made once; :meth:`fill` puts a unit's errors in the
    lines, sets the scales and legends and shows the bands that fit."""

    def __init__(self, panels: list[dict]) -> None:
        from matplotlib.figure import Figure

        self.layout = self.key(panels)
        slots = sum(p["width"] for p in panels) + max(len(panels) - 1, 0)
        width_in = _MARGINS_IN["left"] + _MARGINS_IN["right"] + _SLOT_IN * max(slots, _MIN_SLOTS)
        self.fig = fig = Figure(figsize=(width_in, _HEIGHT_IN), dpi=_VERIFICATION_DPI)
        fig.subplots_adjust(
            left=_MARGINS_IN["left"] / width_in,
            right=1 - _MARGINS_IN["right"] / width_in,
            bottom=_MARGINS_IN["bottom"] / _HEIGHT_IN,
            top=1 - _MARGINS_IN["top"] / _HEIGHT_IN,
            hspace=_GAP_IN / _PANEL_IN,
        )
        self.before, self.after = fig.subplots(2, 1)
        fixed = []
        for ax in (self.before, self.after):
            ax.set_xticks([])
        self.before.set_ylabel("before: dg  [micro-g]", fontsize=9)
        self.after.set_ylabel("after: dg  [micro-g]", fontsize=9)
        self.series: list[tuple] = []  # (axes, row field, line, ring line), in drawing order
        self.legends: dict[tuple, object] = {}  # (axes, labels) -> its legend, made once
        self.shown: list[tuple] = []
        self.bands: list[tuple] = []  # (band, limit in micro-g)
        if not panels:
            fixed.append(self.before.text(0.5, 0.5, "no VP data", ha="center", transform=self.before.transAxes))
        else:
            self.x = np.concatenate([np.append(p["x"], np.nan) for p in panels])[:-1]
            lim_ug = [np.append([r["tolerance_g"] for r in p["rows"]], np.nan) for p in panels]
            self.lim_ug = np.concatenate(lim_ug)[:-1] * 1e6
            for ax, series in ((self.before, _DG_SERIES[:1]), (self.after, _DG_SERIES[1:])):
                for field, label, fmt, colour in series:
                    (line,) = ax.plot([], [], fmt, color=colour, label=label, ms=4)
                    (ring,) = ax.plot([], [], "o", ms=11, mfc="none", mec="red", mew=1.5, label="beyond the limit")
                    self.series.append((ax, field, line, ring))
                fixed += self._decor(ax, panels, titles=ax is self.before, names=ax is self.after)
        self.title = fig.suptitle("", x=_MARGINS_IN["left"] / width_in, y=1 - 0.08 / _HEIGHT_IN, ha="left", va="top")
        fixed += [self.before.xaxis, self.after.xaxis]  # no ticks, no label: nothing drawn
        self.layers = _Layers(fig, fixed, ticks=((self.before.yaxis, True), (self.after.yaxis, True)))

    @staticmethod
    def key(panels: list[dict]) -> tuple:
        """What the fixed artists are made of: per panel its place, title (temperature, visit, limit), position
        names and their places."""
        return tuple(
            (p["x0"], p["width"], _panel_title(p), tuple(r["position"] for r in p["rows"]), tuple(p["x"]))
            for p in panels
        )

    def _decor(self, ax, panels: list[dict], *, titles: bool, names: bool) -> list:
        """The limit bands (shown by :meth:`fill` where they fit the scale), separators, zero line, and the panel
        titles or the position names (the two axes share their x: titles above the upper, names under the lower);
        returns the texts, the fixed artists among them."""
        from matplotlib.patches import Rectangle

        below = ax.get_xaxis_transform()  # x in data, y in axes fraction
        fixed = []
        for k, p in enumerate(panels):
            lim_ug = p["rows"][0]["tolerance_g"] * 1e6
            band = ax.add_patch(Rectangle((p["x0"], -lim_ug), p["width"], 2 * lim_ug, color="0.9", zorder=0))
            self.bands.append((band, lim_ug))
            if titles:
                fixed.append(
                    ax.text(
                        p["x0"] + p["width"] / 2,
                        1.01,
                        _panel_title(p),
                        ha="center",
                        va="bottom",
                        fontsize=7,
                        transform=below,
                    )
                )
            for xi, r in zip(p["x"], p["rows"]) if names else ():
                fixed.append(ax.text(xi, -0.02, r["position"], ha="center", va="top", fontsize=7, transform=below))
            if k:
                ax.axvline(p["x0"] - 0.5, color="0.6", lw=0.8)
        ax.axhline(0, color="k", lw=0.5)  # over the bands, which change: drawn each time as they are
        ax.set_xlim(panels[0]["x0"], panels[-1]["x0"] + panels[-1]["width"])
        return fixed

    def fill(self, panels: list[dict], title: str) -> None:
        """A unit's errors (its ``panels``, of this frame's :meth:`key`) in the lines, each axes scaled to its
        largest error, the bands that fit shown, the legends of what is drawn, and the ``title``."""
        from matplotlib.legend import Legend

        self.title.set_text(title)
        self.shown = []  # the legends to paste: ((after?, labels), legend)
        if not panels:
            return
        for ax in (self.before, self.after):
            handles, ringed = [], False  # the legend: each series, and the first ring drawn
            mine = [s for s in self.series if s[0] is ax]
            dg_ug = [
                np.concatenate([np.append([r[field] for r in p["rows"]], np.nan) for p in panels])[:-1] * 1e6
                for _, field, _, _ in mine
            ]
            finite = np.abs(np.concatenate(dg_ug))
            finite = finite[np.isfinite(finite)]  # (an infinite error has no place on a scale: not drawn)
            name, per_ug = _dg_unit(float(finite.max()) if finite.size else 0.0)
            for (_, _, line, ring), dg in zip(mine, dg_ug):
                bad = np.abs(dg) > self.lim_ug
                dg = np.where(np.isfinite(dg), dg, np.nan) / per_ug
                line.set_data(self.x, dg)
                ring.set_data(self.x[bad], dg[bad])
                handles += [line, ring] if bad.any() and not ringed else [line]
                ringed = ringed or bool(bad.any())
            span = max(float(finite.max()) / per_ug if finite.size else 0.0, 1.0) * 1.15
            ax.set_ylim(-span, span)
            ax.yaxis.label.set_text(f"{'before' if ax is self.before else 'after'}: dg  [{name}]")
            for band, lim_ug in self.bands:
                if band.axes is ax:
                    band.set_y(-lim_ug / per_ug)
                    band.set_height(2 * lim_ug / per_ug)
                    band.set_visible(lim_ug / per_ug < span)
            labels = tuple(h.get_label() for h in handles)
            if (ax, labels) not in self.legends:  # outside the axes, at a fixed place: pasted as pixels
                up, at = ("upper left", (0.0, 1.2)) if ax is self.before else ("upper right", (1.0, 1.14))
                self.legends[ax, labels] = Legend(
                    ax,
                    handles,
                    labels,
                    loc=up,  # type: ignore[arg-type]  # one of the two literals above
                    bbox_to_anchor=at,
                    ncols=4,
                    fontsize=7,
                    frameon=False,
                    borderaxespad=0,
                )
            self.shown.append(((ax is self.after, labels), self.legends[ax, labels]))


def _dg_unit(peak_ug: float) -> tuple[str, float]:
    """The unit of a verification axes whose largest error is ``peak_ug`` (micro-g) and its size in micro-g: the
    coarsest of micro-g, milli-g and g that keeps its tick labels under five digits (a consumer part's errors before
    compensation reach 10^5 micro-g, whose tick labels would push the axis label off the figure)."""
    for name, per_ug in (("micro-g", 1.0), ("milli-g", 1e3)):
        if peak_ug * 1.15 / per_ug < 1e4:
            return name, per_ug
    return "g", 1e6


def _panel_title(p: dict) -> str:
    """A panel's title: its temperature, its visit when the temperature has several, and its limit (micro-g)."""
    visit = f", visit {p['visit']}" if p["visits"] > 1 else ""
    return f"{p['temp_c']:+.1f} C{visit} (limit {p['rows'][0]['tolerance_g'] * 1e6:.0f})"


def _row_dict(r) -> dict:
    """A verification row as a dict (rows come as VerificationRow objects or as a passport's dicts)."""
    return r if isinstance(r, dict) else r.to_dict()


def _panels(rows: list[dict]) -> list[dict]:
    """The verification rows (dicts) by visit (:func:`pipeline.verify.verification_visits`: coldest first, the
    visits of one temperature in time order), laid out on the x axis: each visit's ``rows``, their ``x`` (one slot
    each, centred in the panel), the panel's left edge ``x0`` and ``width`` (slots: at least
    :data:`_MIN_PANEL_SLOTS`, room for the title), ``temp_c``, ``visit`` and ``visits``; one empty slot between
    panels."""
    from pipeline.verify import verification_visits

    panels, x0 = [], 0.0
    for v in verification_visits(rows):
        width = max(len(v["rows"]), _MIN_PANEL_SLOTS)
        x = x0 + (width - len(v["rows"])) / 2 + 0.5 + np.arange(len(v["rows"]))
        panels.append({**v, "x": x, "x0": x0, "width": width})
        x0 += width + 1
    return panels


#: Rows of the constants figure: (key, y label, unit); each followed by the row of its residuals from the model,
#: in the same unit.
_CONSTANT_ROWS = (
    ("gain", "gain K_ii\nchange [ppm]", "ppm"),
    ("cross", "cross-axis K_ij\nchange [ppm of K_ii]", "ppm of K_ii"),
    ("offset", "offset U0_i\nchange [micro-g]", "micro-g"),
)


def constant_changes(K: np.ndarray, U0: np.ndarray, K0: np.ndarray, U00: np.ndarray) -> dict[str, np.ndarray]:
    """The constants ``K`` (n, 3, 3) V/g and ``U0`` (n, 3) V as changes from the normal-temperature ``K0``, ``U00``
    in engineering units: ``gain`` (n, 3) in ppm of the axis gain, ``cross`` (n, 3, 2) the two cross-axis terms
    of each row in ppm of its gain (columns in axis order, the diagonal left out), ``offset`` (n, 3) in micro-g
    (the offset's change over the axis gain)."""
    K, U0 = np.asarray(K, float), np.asarray(U0, float)
    gain0 = np.diag(np.asarray(K0, float))
    dK = (K - np.asarray(K0, float)) / gain0[None, :, None] * 1e6
    off = ~np.eye(3, dtype=bool)
    return {
        "gain": np.einsum("nii->ni", dK),
        "cross": dK[:, off].reshape(len(K), 3, 2),
        "offset": (U0 - np.asarray(U00, float)) / gain0 * 1e6,
    }


def plot_constants(passport: Passport | dict, path: str | Path, *, title: str = "") -> Path:
    """:func:`constants_figure` written to ``path`` (PNG), drawn in this thread's figure (:class:`_ConstantsFrame`,
    made once per thread and filled again for each passport)."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg

    frame = _constants_frame()
    fig = constants_figure(passport, title=title, frame=frame)
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    if fig is frame.fig:
        frame.layers.save(path)
    else:  # no values to put in the frame: a figure of its own
        FigureCanvasAgg(fig).print_png(path, pil_kwargs={"compress_level": 1})
    return path


def warm_up() -> None:
    """Draw this thread's constants figure once, empty (its fixed artists and its legends kept as pixels, the fonts
    loaded), so that its first figure costs what the others do: a figure worker does it at its start, beside its
    caller's segmentation."""
    _constants_frame().layers.save(io.BytesIO())


def _constants_frame() -> _ConstantsFrame:
    """This thread's :class:`_ConstantsFrame` (made at the first call)."""
    frame = getattr(_FRAMES, "constants", None)
    if frame is None:
        frame = _FRAMES.constants = _ConstantsFrame()
    return frame


class _Layers:
    """A figure drawn as its fixed artists, kept as pixels after its first drawing, and the others drawn over them
    each time (matplotlib's blitting: those are "animated", left out of the canvas's drawing): a figure filled
    again for each unit draws only what a unit changes. Fixed: the axes' backgrounds and titles and the artists
    ``fixed``; the others (frames, ticks, labels, lines, legends, the figure's title) are drawn in the order the
    figure's own drawing has (axes in turn, each one's artists by zorder, then the figure's), so the PNG is the one
    ``print_png`` writes of the whole figure when no fixed artist covers a changing one."""

    def __init__(self, fig, fixed: list, best_legends: tuple = (), ticks: tuple = (), keyed: tuple = ()) -> None:
        from matplotlib.backends.backend_agg import FigureCanvasAgg

        self.fig, self.canvas = fig, FigureCanvasAgg(fig)
        texts = _TextPixels(fig)
        self.ticks = {id(axis): _Ticks(axis, texts, placed) for axis, placed in ticks}  # (axis, label placed?)
        self.keyed = {id(axis): region for axis, region in keyed}  # axes drawn as pixels per view interval
        self._fixed_ids = {id(a) for a in fixed} | {id(fig.patch)}
        for ax in fig.axes:
            self._fixed_ids |= {id(ax.patch), id(ax.title), id(ax)}
        self._pixels = None  # the fixed artists drawn, after the first figure
        self.best_legends = best_legends
        self._pasted: dict = {}  # key -> the pixels of an artist drawn as :meth:`_paste`
        self._legend_sizes: dict = {}  # legend -> its extent (its size)
        for legend in best_legends:
            legend.set_visible(False)  # drawn by _paste_legends

    def _changing(self) -> list:
        changing = []
        for ax in self.fig.axes:
            mine = (a for a in ax.get_children() if id(a) not in self._fixed_ids)
            changing += sorted(mine, key=lambda a: a.get_zorder())
        changing += [a for a in self.fig.get_children() if id(a) not in self._fixed_ids]
        for artist in changing:
            artist.set_animated(True)
        return changing

    def save(self, path: Path | BinaryIO, pasted: tuple = ()) -> None:
        """Draw the figure as it is now and write it to ``path`` (PNG: :func:`_write_png`). ``pasted``: ``(key,
        artist)`` pairs of artists outside the figure's children whose look ``key`` fixes (legends of one content at
        one place), drawn as their pixels under the changing artists (the pixels of the first drawing of each key)."""
        changing = self._changing()
        for ax in self.fig.axes:
            ax.viewLim  # noqa: B018 -- applies a pending autoscale (done by the axes' own drawing otherwise)
        renderer = self.canvas.get_renderer()
        if self._pixels is None:
            self.canvas.draw()
            renderer = self.canvas.get_renderer()
            for drawer in self.ticks.values():
                drawer.draw_label(renderer)
            self._pixels = self.canvas.copy_from_bbox(self.fig.bbox)
        else:
            self.canvas.restore_region(self._pixels)
        self._paste_legends(renderer)
        for key, artist in pasted:
            self._paste(key, artist, renderer)
        for artist in changing:
            ticks, region = self.ticks.get(id(artist)), self.keyed.get(id(artist))
            if ticks is not None:
                ticks.draw(renderer)
            elif region is not None:  # its look fixed by its view interval (its ticks and their labels)
                self._paste((id(artist), *artist.get_view_interval()), artist, renderer, region)
            else:
                artist.draw(renderer)
        _write_png(path, np.asarray(self.canvas.buffer_rgba()), self.fig.dpi)

    def _paste_legends(self, renderer) -> None:
        """Each of ``best_legends`` (placed "best": their contents fixed, their places not) where matplotlib would
        place it for the lines of its axes now (:data:`_LEGEND_PLACES` in turn: the first of those covering fewest
        of the lines' points and crossing fewest of them), as its pixels drawn once for each place (the legends'
        texts were a fifth of the constants figure's drawing). Under the changing artists: a line through a legend
        is drawn over it."""
        from matplotlib.transforms import Bbox

        for k, legend in enumerate(self.best_legends):
            ax = legend.axes
            if k not in self._legend_sizes:  # its contents fixed: measured once
                self._legend_sizes[k] = legend.get_window_extent(renderer)
            size = self._legend_sizes[k]
            pad = legend.borderaxespad * renderer.points_to_pixels(legend.prop.get_size_in_points())
            inside = ax.bbox.padded(-pad)
            paths = [line.get_transform().transform_path(line.get_path()) for line in ax.get_lines()]
            least = None
            for place, anchor in _LEGEND_PLACES:
                box = Bbox.from_bounds(0, 0, size.width, size.height).anchored(anchor, container=inside)
                covered = sum(box.count_contains(p.vertices) + p.intersects_bbox(box, filled=False) for p in paths)
                if least is None or covered < least[0]:
                    least = (covered, place)
                if covered == 0:
                    break
            assert least is not None
            if (k, least[1]) not in self._pasted:
                legend.set_loc(least[1])
            legend.set_visible(True)
            self._paste((k, least[1]), legend, renderer)
            legend.set_visible(False)

    def _paste(self, key, artist, renderer, region=None) -> None:
        """``artist`` as the pixels of its first drawing under ``key`` (drawn now when there are none): those of its
        extent, or of ``region`` (a Bbox in pixels where it alone draws)."""
        pixels = self._pasted.get(key)
        if pixels is None:
            if len(self._pasted) >= _MOST_KEPT:  # a long-lived process drawing many programs: made again as needed
                self._pasted.clear()
            artist.draw(renderer)
            where = artist.get_window_extent(renderer).padded(2) if region is None else region
            self._pasted[key] = self.canvas.copy_from_bbox(where)
        else:
            self.canvas.restore_region(pixels)


#: At most this many artists' pixels are kept per figure (legends per place, temperature axes per limits; 32 times as
#: many texts): ~40 MB at most, cleared when full.
_MOST_KEPT = 256


def _write_png(path: Path | BinaryIO, rgba: np.ndarray, dpi: float) -> None:
    """``rgba`` (rows from the top, 8 bits a channel) as a PNG at ``dpi``, with the software text matplotlib writes:
    its rows unfiltered, zlib's fastest level (PIL's encoder tries every filter on every row: ~25 ms of a constants
    figure's 30, at any level; unfiltered rows of a figure compress as well)."""
    import struct
    import zlib

    import matplotlib

    def chunk(kind: bytes, data: bytes) -> bytes:
        return struct.pack(">I", len(data)) + kind + data + struct.pack(">I", zlib.crc32(kind + data))

    height, width = rgba.shape[:2]
    rows = np.empty((height, 1 + 4 * width), np.uint8)
    rows[:, 0] = 0  # filter: none
    rows[:, 1:] = rgba.reshape(height, -1)
    per_metre = int(dpi / 0.0254 + 0.5)
    software = f"Matplotlib version{matplotlib.__version__}, https://matplotlib.org/"
    png = b"".join(
        [
            b"\x89PNG\r\n\x1a\n",
            chunk(b"IHDR", struct.pack(">IIBBBBB", width, height, 8, 6, 0, 0, 0)),  # 8-bit RGBA
            chunk(b"tEXt", b"Software\0" + software.encode("latin-1")),
            chunk(b"pHYs", struct.pack(">IIB", per_metre, per_metre, 1)),
            chunk(b"IDAT", zlib.compress(rows.data, 1)),
            chunk(b"IEND", b""),
        ]
    )
    if isinstance(path, (str, Path)):
        Path(path).write_bytes(png)
    else:
        path.write(png)


class _Ticks:
    """An axis's major ticks drawn as its own drawing draws them (the same locations and labels: its locator and
    formatter, the ticks in its view interval), for less: its grid lines and its tick marks each as one line, its
    tick labels as pixels (:class:`_TextPixels`; the texts were 3/4 of a constants figure's ticks). Its axis label
    is either fixed (``placed`` False: at coordinates of its own, drawn once with the fixed pixels by
    :meth:`draw_label`) or placed as matplotlib places a y axis's label on the left (its tick labels' and left
    spine's extents, less its pad) and pasted as pixels too. An axis with ticks on its other side, a scale other than
    linear or an offset text (placed by its tick labels' extents) is drawn by matplotlib."""

    def __init__(self, axis, texts: _TextPixels, placed: bool = False) -> None:
        from matplotlib.lines import Line2D

        self.axis, self.texts = axis, texts
        tick = axis.get_major_ticks(1)[0]  # its ticks' look (tick_params, grid), of every tick
        self.placed = placed
        self.simple = not (tick.tick2line.get_visible() or tick.label2.get_visible())
        self.simple &= not placed or (axis.axis_name == "y" and axis.get_label_position() == "left")
        self.lines = []  # (line, across): the grid lines from 0 to 1 across the axes, the tick marks at 0
        for template, across in ((tick.gridline, (0.0, 1.0)), (tick.tick1line, (0.0,))):
            if template.get_visible():
                line = Line2D([], [])
                line.update_from(template)  # its style, transform and clipping
                line.set_figure(axis.get_figure(root=False))
                self.lines.append((line, np.array(across)))
        self.label = tick.label1 if tick.label1.get_visible() else None  # the tick labels' style and transform
        self.style = _TextPixels.style(tick.label1)
        self.label_style = _TextPixels.style(axis.label)

    def draw_label(self, renderer) -> None:
        """A fixed axis label, drawn once with the fixed pixels (placed by its coordinates, not by the tick labels);
        a placed one is drawn with the ticks."""
        if not self.placed:
            self.axis.label.draw(renderer)
            self.axis.label.set_visible(False)

    def draw(self, renderer) -> None:
        axis = self.axis
        locs = np.asarray(axis.get_majorticklocs(), float)
        formatter = axis.get_major_formatter()
        labels = formatter.format_ticks(locs)  # all of them, as the axis does: they decide the format
        if not self.simple or axis.get_scale() != "linear" or formatter.get_offset():
            axis.draw(renderer)
            return
        lo, hi = sorted(axis.get_view_interval())
        slack = (hi - lo) * 1e-10  # the axis's own tolerance at the ends of its view interval
        kept = (locs >= lo - slack) & (locs <= hi + slack)
        locs = locs[kept]
        along_x = axis.axis_name == "x"
        for line, across in self.lines:  # one stroke per tick, NaN between them
            a = np.tile(np.append(across, np.nan), len(locs))
            b = np.repeat(locs, len(across) + 1)
            b[len(across) :: len(across) + 1] = np.nan
            line.set_data((b, a) if along_x else (a, b))
            line.draw(renderer)
        extents = []
        if self.label is not None and len(locs):
            at = self.label.get_position()[1 if along_x else 0]
            points = np.column_stack([locs, np.full(len(locs), at)] if along_x else [np.full(len(locs), at), locs])
            where = self.label.get_transform().transform(points)
            shown = [label for label, keep in zip(labels, kept) if keep]
            extents = self.texts.draw(renderer, self.label, self.style, shown, where)
        if self.placed and axis.label.get_visible() and axis.label.get_text():
            from matplotlib.transforms import Bbox

            label, ax = axis.label, axis.axes
            left = Bbox.union([*extents, ax.spines.get("left", ax).get_window_extent()]).x0
            label.set_position((left - axis.labelpad * axis.get_figure(root=True).dpi / 72, label.get_position()[1]))
            where = label.get_transform().transform([label.get_position()])
            self.texts.draw(renderer, label, self.label_style, [label.get_text()], where)


#: Texts pasted as pixels are drawn at positions rounded to 1 / _TEXT_STEPS pixel (matplotlib draws glyphs at 1/64):
#: within 1/4 pixel of their place; each text is drawn once per place within a pixel (~2 ms: 4 rather than 16
#: places at 1/4 pixel, a fifth of the constants figure's CPU at a run's first units).
_TEXT_STEPS = 2


class _TextPixels:
    """Short texts (tick labels, axis labels) drawn as the pixels of their first drawing: per style, text and position
    within a pixel (to 1 / :data:`_TEXT_STEPS`), drawn once by matplotlib on a transparent canvas of their own and
    then blended in at each place (matplotlib draws a text glyph by glyph each time: ~0.25 ms a glyph)."""

    _PAD = 8  # pixels around a text's extent on its canvas (its glyphs' ink may reach a pixel or two beyond)

    def __init__(self, fig) -> None:
        from matplotlib.text import Text
        from matplotlib.transforms import IdentityTransform

        self.probe = Text()
        self.probe.set_figure(fig)
        self.identity = IdentityTransform()
        self.images: dict[tuple, tuple] = {}  # key -> (pixels or None, dx, dy, extent around the point)

    @staticmethod
    def style(text) -> tuple:
        """What a text's pixels depend on besides its string and place."""
        return (
            text.get_fontproperties(),
            str(text.get_color()),
            text.get_alpha(),
            text.get_horizontalalignment(),
            text.get_verticalalignment(),
            text.get_rotation(),
            text.get_rotation_mode(),
            text.get_linespacing(),
        )

    def draw(self, renderer, template, style: tuple, texts: list[str], where: np.ndarray) -> list:
        """``texts`` in ``template``'s look (its ``style``) at ``where`` (pixels: the points of their transform);
        their extents (as ``get_window_extent``'s, at ``where``)."""
        extents = []
        gc = renderer.new_gc()
        try:
            where = np.asarray(where, float)
            snapped = np.round(where * _TEXT_STEPS) / _TEXT_STEPS
            whole = np.floor(snapped)
            for text, (x, y), (fx, fy), point in zip(texts, whole, snapped - whole, where):
                key = (style, text, fx, fy)
                if key not in self.images:
                    if len(self.images) >= 32 * _MOST_KEPT:
                        self.images.clear()
                    self.images[key] = self._render(renderer, template, text, fx, fy)
                pixels, dx, dy, extent = self.images[key]
                if pixels is not None:
                    renderer.draw_image(gc, int(x) + dx, int(y) + dy, pixels)
                extents.append(extent.translated(*point))
        finally:
            gc.restore()
        return extents

    def _probe(self, template, text: str, x: float, y: float):
        probe = self.probe
        probe.update_from(template)
        probe.set_rotation_mode(template.get_rotation_mode())  # not among update_from's
        probe.set_transform(self.identity)
        probe.set_position((x, y))
        probe.set_text(text)
        return probe

    def _render(self, renderer, template, text: str, fx: float, fy: float) -> tuple:
        """The pixels of ``text`` drawn with its point at (``fx``, ``fy``) within a pixel (bottom row first), where
        their lower left pixel is from that pixel, and the text's extent around its point."""
        from matplotlib.backends.backend_agg import RendererAgg

        extent = self._probe(template, text, 0.0, 0.0).get_window_extent(renderer)
        if not text:
            return None, 0, 0, extent
        x0, y0 = self._PAD - int(np.floor(extent.x0)), self._PAD - int(np.floor(extent.y0))
        width, height = int(np.ceil(extent.x1)) + x0 + self._PAD, int(np.ceil(extent.y1)) + y0 + self._PAD
        canvas = RendererAgg(width, height, renderer.dpi)  # transparent
        self._probe(template, text, x0 + fx, y0 + fy).draw(canvas)
        rgba = np.asarray(canvas.buffer_rgba())
        rows, cols = np.flatnonzero(rgba[..., 3].any(axis=1)), np.flatnonzero(rgba[..., 3].any(axis=0))
        if not rows.size:
            return None, 0, 0, extent
        pixels = rgba[rows[-1] : rows[0] - 1 if rows[0] else None : -1, cols[0] : cols[-1] + 1].copy()  # bottom up
        return pixels, int(cols[0]) - x0, height - 1 - int(rows[-1]) - y0, extent


#: matplotlib's places of a legend (its location codes 1-10: the order in which "best" tries them) and where each is
#: anchored in its axes.
_LEGEND_PLACES: tuple[tuple[str, Literal["NE", "NW", "SW", "SE", "E", "W", "S", "N", "C"]], ...] = (
    ("upper right", "NE"),
    ("upper left", "NW"),
    ("lower left", "SW"),
    ("lower right", "SE"),
    ("right", "E"),
    ("center left", "W"),
    ("center right", "E"),
    ("lower center", "S"),
    ("upper center", "N"),
    ("center", "C"),
)


def constants_figure(passport: Passport | dict, *, title: str = "", frame: _ConstantsFrame | None = None):
    """The core figure of a thermal calibration: the constants found on each plateau against temperature (points,
    with their standard uncertainty as error bars where the passport has it), the fitted thermal model (line) and
    its residuals (plateau minus model, the row under each), per axis (columns x, y, z): gain K_ii in ppm,
    cross-axis K_ij in ppm of the gain, offset U0_i in micro-g, all as changes from the normal-temperature
    constants. ``passport``: a :class:`pipeline.passport.document.Passport` (a document is loaded once here); the
    per-plateau constants are read from its document as stored (``per_plateau``). ``frame``: the figure to fill
    (its previous values replaced), else a new one."""
    from pipeline.passport.document import load_passport

    passport = load_passport(passport)
    pp = passport.document.get("per_plateau") or []
    K0, U00 = passport.K, passport.U0
    T0 = passport.normal_temp_c
    span = passport.valid_temp_c or (T0, T0)
    if pp or span[1] > span[0]:
        # a method without plateau constants (differential) shows its model over the valid range, no points
        T = np.array([p["temp_c"] for p in pp], float)
        points = constant_changes(
            np.asarray([p["K"] for p in pp], float).reshape(-1, 3, 3),
            np.asarray([p["U0"] for p in pp], float).reshape(-1, 3),
            K0,
            U00,
        )
        sig = _plateau_sigmas(passport.uncertainty, len(pp), K0)
        lo, hi = min([T0, span[0], *T.tolist()]), max([T0, span[1], *T.tolist()])
        grid = np.linspace(lo, hi, 121)
        model = passport.thermal_model
        at_grid = constant_changes(*model.constants_at(grid), K0, U00)
        at_T = constant_changes(*model.constants_at(T), K0, U00)
        frame = frame or _ConstantsFrame()
        frame.fill(T, points, sig, grid, at_grid, at_T, (lo, hi))
        fig = frame.fig
    else:
        fig, axes = _constants_axes()
        axes[0, 0].text(
            0.5, 0.5, "no plateau constants and no temperature range", ha="center", transform=axes[0, 0].transAxes
        )
    described = passport.thermal_model.to_dict()
    kind, order = described.get("kind", ""), described.get("order")
    model_name = f"polynomial of order {order}" if kind == "polynomial" else kind.replace("_", " ")
    title = title or f"Constants per plateau against temperature, thermal model: {model_name}"
    fig.suptitle(title + ("" if pp else " (no per-plateau constants: the model alone)"), fontsize=11)
    return fig


#: Each thread's figures to fill again (:func:`plot_constants`, :func:`plot_verification`): a figure object is drawn
#: by one thread at a time.
_FRAMES = threading.local()


def _constants_axes():
    """The constants figure and its 6 x 3 axes (values and residuals per row of :data:`_CONSTANT_ROWS`, per axis).
    Not sharex: a shared x axis shares its tick locator, and every axes would make the bottom row's tick objects
    (18 axes' ticks were most of the drawing time); the rows above take the bottom row's limits instead."""
    from matplotlib.figure import Figure

    fig = Figure(figsize=(12, 10.5), dpi=90)
    axes = fig.subplots(6, 3, gridspec_kw={"height_ratios": [3, 1.3] * 3})
    fig.subplots_adjust(left=0.09, right=0.99, bottom=0.05, top=0.92, hspace=0.12, wspace=0.22)
    return fig, axes


#: Where the constants figure's axis labels are (axes fraction): left of tick labels of up to 7 characters (the
#: formatter's longest before it writes an offset or a power of ten), under the temperature tick labels.
_YLABEL_AT = (-0.21, 0.5)
_XLABEL_AT = (0.5, -0.3)


class _ConstantsFrame:
    """The constants figure with its axes, lines, legends, labels and locators made once (making the 18 axes and
    their tick objects was ~2/3 of the figure's time); :meth:`fill` puts a passport's values in the lines and sets
    the limits, so each figure drawn is the one made afresh for those values."""

    def __init__(self) -> None:
        from matplotlib.ticker import MaxNLocator, NullLocator

        self.fig, self.axes = _constants_axes()
        self.series: dict[tuple[int, int], list] = {}  # (row, axis) -> per series: points, bars, model, residuals
        self.zeros = []  # the zero line of each residual axes
        axis = "xyz"
        for r, (key, label, unit) in enumerate(_CONSTANT_ROWS):
            for i in range(3):
                ax, res = self.axes[2 * r, i], self.axes[2 * r + 1, i]
                others = [j for j in range(3) if j != i]
                lines = []
                for k in range(2 if key == "cross" else 1):
                    colour = f"C{k}" if key == "cross" else "C0"
                    name = f"K{axis[i]}{axis[others[k]]}" if key == "cross" else None
                    pts = ax.plot(
                        [], [], "o", ms=4, color=colour, label=f"{name} per plateau" if name else "per plateau"
                    )
                    bars = ax.plot([], [], "-", color=colour, lw=1)
                    fit = ax.plot([], [], "-", color=colour, lw=1, label=f"{name} model" if name else "thermal model")
                    rpts = res.plot([], [], "o", ms=3, color=colour)
                    rbars = res.plot([], [], "-", color=colour, lw=1)
                    lines.append([*pts, *bars, *fit, *rpts, *rbars])
                self.series[r, i] = lines
                self.zeros.append(res.axhline(0, color="k", lw=0.5))
                ax.grid(axis="y", alpha=0.3)
                res.grid(axis="y", alpha=0.3)
                if i == 0:
                    ax.set_ylabel(label, fontsize=8)
                    res.set_ylabel(f"residual\n[{unit}]", fontsize=8)
                for a in (ax, res):  # at fixed places: placing them measured every tick label once more
                    a.yaxis.set_label_coords(*_YLABEL_AT)
                if r == 0:
                    ax.set_title(f"axis {axis[i]}", fontsize=10)
                if key == "cross" or (r == 0 and i == 0):
                    ax.legend(fontsize=6, loc="best", frameon=False)
                ax.tick_params(labelsize=7)
                res.tick_params(labelsize=7)
                ax.yaxis.set_major_locator(MaxNLocator(5))
                res.yaxis.set_major_locator(MaxNLocator(3))
        for ax in self.axes[:-1].flat:  # temperature ticks and labels on the bottom row only
            ax.xaxis.set_major_locator(NullLocator())
        for ax in self.axes[-1]:
            ax.xaxis.set_major_locator(MaxNLocator(6))
            ax.set_xlabel("temperature [C]", fontsize=8)
            ax.xaxis.set_label_coords(*_XLABEL_AT)
        self.title = self.fig.suptitle("", fontsize=11)
        self._layers: _Layers | None = None

    @property
    def layers(self) -> _Layers:
        """The figure as :class:`_Layers` (made at the first use: a figure whose artists are animated draws only
        its fixed ones in a plain ``print_png``)."""
        if self._layers is None:
            from matplotlib.transforms import Bbox

            legends = tuple(ax.get_legend() for ax in self.axes.flat if ax.get_legend() is not None)
            bottom = self.axes[-1]
            edges = [0.0] + [(a.bbox.x1 + b.bbox.x0) / 2 for a, b in zip(bottom[:-1], bottom[1:])] + [self.fig.bbox.x1]
            self._layers = _Layers(
                self.fig,
                [ax.xaxis for ax in self.axes[:-1].flat],  # no ticks, no label: nothing drawn
                best_legends=legends,
                ticks=tuple((ax.yaxis, False) for ax in self.axes.flat),
                # under each axes of the bottom row, between the middles of the gaps: its temperature axis alone (and
                # the axes' frame over it, drawn after); the same limits for every unit of one program
                keyed=tuple(
                    (ax.xaxis, Bbox.from_extents(x0, 0, x1, ax.bbox.y0 + 2))
                    for ax, x0, x1 in zip(bottom, edges[:-1], edges[1:])
                ),
            )
        return self._layers

    def fill(self, T, points, sig, grid, at_grid, at_T, span: tuple[float, float]) -> None:
        """The plateau temperatures ``T`` and changes ``points`` (:func:`constant_changes`), their ``sig`` (or None),
        the model at ``grid`` and at ``T``, the temperature ``span`` (lo, hi) shown with a 4 % margin."""
        for (r, i), lines in self.series.items():
            key = _CONSTANT_ROWS[r][0]
            for k, (pts, bars, fit, rpts, rbars) in enumerate(lines):
                y = points[key][:, i, k] if key == "cross" else points[key][:, i]
                yT = at_T[key][:, i, k] if key == "cross" else at_T[key][:, i]
                e = None if sig is None else (sig[key][:, i, k] if key == "cross" else sig[key][:, i])
                pts.set_data(T, y)
                bars.set_data(*_bars(T, y, e))
                fit.set_data(grid, at_grid[key][:, i, k] if key == "cross" else at_grid[key][:, i])
                rpts.set_data(T, y - yT)
                rbars.set_data(*_bars(T, y - yT, e))
        lo, hi = span
        pad = 0.04 * (hi - lo) if hi > lo else 1.0
        for zero in self.zeros:  # measured again from the previous limits, y = 0 would come back as ~1e-16
            zero.set_visible(False)
        for ax in self.axes.flat:
            ax.relim(visible_only=True)
        for zero in self.zeros:
            zero.set_visible(True)
            zero.axes.update_datalim([(0.0, 0.0)], updatex=False)
        for ax in self.axes.flat:
            ax.set_xlim(lo - pad, hi + pad)
            ax.autoscale_view(scalex=False)


def _bars(x: np.ndarray, y: np.ndarray, e: np.ndarray | None) -> tuple[np.ndarray, np.ndarray]:
    """Error bars ``y +- e`` at ``x`` (where finite) as one line of vertical strokes (NaN between them): one
    artist where ``errorbar`` makes a line collection and caps per series (a figure of 18 axes draws ~50 series);
    no points without ``e``."""
    if e is None or not np.isfinite(e).any():
        return np.empty(0), np.empty(0)
    return np.repeat(x, 3), np.stack([y - e, y + e, np.full_like(y, np.nan)], axis=1).ravel()


def _plateau_sigmas(uncertainty: dict | None, n: int, K0: np.ndarray) -> dict[str, np.ndarray] | None:
    """The per-plateau standard uncertainties of a passport (its ``uncertainty``) in the units of
    :func:`constant_changes`, or None when it has none (NaN where one plateau has none)."""
    rows = ((uncertainty or {}).get("per_plateau")) or []
    if not n or len(rows) != n:
        return None
    K = np.array([r["K"] if r.get("K") is not None else np.full((3, 3), np.nan) for r in rows], float)
    U0 = np.array([r["U0"] if r.get("U0") is not None else np.full(3, np.nan) for r in rows], float)
    return _sigma_changes(K, U0, K0)


def _sigma_changes(K_sigma: np.ndarray, U0_sigma: np.ndarray, K0: np.ndarray) -> dict[str, np.ndarray]:
    gain0 = np.diag(np.asarray(K0, float))
    s = K_sigma / np.abs(gain0)[None, :, None] * 1e6
    off = ~np.eye(3, dtype=bool)
    return {
        "gain": np.einsum("nii->ni", s),
        "cross": s[:, off].reshape(len(s), 3, 2),
        "offset": U0_sigma / np.abs(gain0) * 1e6,
    }
