"""Figures (PNG). matplotlib is imported lazily, so the library imports without it; figures are made as
``matplotlib.figure.Figure`` objects (no pyplot state), so they can be drawn from several threads at once."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from pipeline.thermal import cluster_temperatures

#: The series of the verification figure: row attribute (g), legend label, matplotlib format, colour.
_DG_SERIES = (("dg_uncompensated_g", "uncompensated", "o-", "C0"), ("dg_method1_g", "method 1", "s-", "C1"),
              ("dg_method2_g", "method 2", "^--", "C2"))
#: Width of one verification position on the x axis of the figure (in), and the margins around the axes (in):
#: fixed, so no layout pass (``tight_layout`` measured every text once more: 40 % of the figure's time).
_SLOT_IN = 0.42
_MARGINS_IN = {"left": 0.85, "right": 0.15, "bottom": 0.35, "top": 0.95}
_HEIGHT_IN = 3.6
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
    """VP gravity-module errors before and after compensation, per verification temperature (like seed 000's
    Fig. 6-7): dg in micro-g at each verification position, uncompensated, method 1 and method 2, over the
    tolerance band. The temperatures are panels side by side in one axes (shared dg scale), each titled with its
    temperature and tolerance and set apart by a vertical line.

    Drawn for throughput (a fleet draws one per unit): one axes, fixed margins (no layout pass), the position
    names as plain texts (no tick objects), one Agg draw straight to the PNG (fast zlib level), legend at a fixed
    place (no "best" search): about 0.1 s, a quarter of the earlier figure (one axes per temperature,
    ``tight_layout``, ``savefig``).
    """
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure
    from matplotlib.patches import Rectangle

    path = Path(path)
    panels = _panels(rows)
    slots = sum(p["width"] for p in panels) + max(len(panels) - 1, 0)
    width_in = _MARGINS_IN["left"] + _MARGINS_IN["right"] + _SLOT_IN * max(slots, _MIN_SLOTS)
    fig = Figure(figsize=(width_in, _HEIGHT_IN), dpi=_VERIFICATION_DPI)
    fig.subplots_adjust(left=_MARGINS_IN["left"] / width_in, right=1 - _MARGINS_IN["right"] / width_in,
                        bottom=_MARGINS_IN["bottom"] / _HEIGHT_IN, top=1 - _MARGINS_IN["top"] / _HEIGHT_IN)
    ax = fig.add_subplot()
    ax.set_xticks([])
    if not panels:
        ax.text(0.5, 0.5, "no VP data", ha="center", transform=ax.transAxes)
    else:
        # the panels' points in one array each, a NaN between panels so that no line joins two temperatures
        x = np.concatenate([np.append(p["x"], np.nan) for p in panels])[:-1]
        for attr, label, fmt, colour in _DG_SERIES:
            dg_ug = np.concatenate([np.append([getattr(r, attr) for r in p["rows"]], np.nan) for p in panels])[:-1]
            ax.plot(x, dg_ug * 1e6, fmt, color=colour, label=label, ms=4)
        below = ax.get_xaxis_transform()  # x in data, y in axes fraction
        for k, p in enumerate(panels):
            lim_ug = p["rows"][0].tolerance_g * 1e6
            band = ax.add_patch(Rectangle((p["x0"], -lim_ug), p["width"], 2 * lim_ug, color="0.9", zorder=0,
                                          label="tolerance"))
            ax.text(p["x0"] + p["width"] / 2, 1.02, f"{p['temp_c']:+.1f} C (+-{lim_ug:.0f} ug)", ha="center",
                    va="bottom", fontsize=9, transform=below)
            for xi, r in zip(p["x"], p["rows"]):
                ax.text(xi, -0.02, r.position, ha="center", va="top", fontsize=7, transform=below)
            if k:
                ax.axvline(p["x0"] - 0.5, color="0.6", lw=0.8)
        ax.axhline(0, color="k", lw=0.5)
        ax.set_xlim(panels[0]["x0"], panels[-1]["x0"] + panels[-1]["width"])
        handles = ax.get_lines()[:len(_DG_SERIES)] + [band]
        # a row of its own under the title (left-aligned with the axes), above the panel titles
        fig.legend(handles=handles, loc="upper left", ncols=len(handles), fontsize=7, frameon=False,
                   bbox_to_anchor=(_MARGINS_IN["left"] / width_in, 1 - 0.38 / _HEIGHT_IN), borderaxespad=0)
    ax.set_ylabel("dg = |a| - 1  [micro-g]")
    fig.suptitle(title or "Gravity-module error at the verification positions", x=_MARGINS_IN["left"] / width_in,
                 y=1 - 0.08 / _HEIGHT_IN, ha="left", va="top")
    path.parent.mkdir(parents=True, exist_ok=True)
    FigureCanvasAgg(fig).print_png(path, pil_kwargs={"compress_level": 1})
    return path


def _panels(rows) -> list[dict]:
    """The verification rows by temperature cluster (coldest first; time order within), laid out on the x axis:
    ``rows``, their ``x`` (one slot each, centred in the panel), the panel's left edge ``x0`` and ``width``
    (slots: at least :data:`_MIN_PANEL_SLOTS`, room for the title), its mean temperature ``temp_c`` (C); one
    empty slot between panels."""
    if not len(rows):
        return []
    labels = cluster_temperatures(np.array([r.temp_c for r in rows], dtype=float))
    panels, x0 = [], 0.0
    for c in range(int(labels.max()) + 1):
        sel = [r for r, lab in zip(rows, labels) if lab == c]
        width = max(len(sel), _MIN_PANEL_SLOTS)
        x = x0 + (width - len(sel)) / 2 + 0.5 + np.arange(len(sel))
        panels.append({"rows": sel, "x": x, "x0": x0, "width": width,
                       "temp_c": float(np.mean([r.temp_c for r in sel]))})
        x0 += width + 1
    return panels
