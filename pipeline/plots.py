"""Figures (PNG). matplotlib is imported lazily, so the library imports without it; figures are made as
``matplotlib.figure.Figure`` objects (no pyplot state), so they can be drawn from several threads at once."""

from __future__ import annotations

from pathlib import Path

import numpy as np


def new_figure(nrows: int, ncols: int, **subplots_kw):
    """A figure of its own (not registered with pyplot) and its axes grid, for writing a PNG with ``savefig``."""
    from matplotlib.figure import Figure

    fig = Figure(figsize=subplots_kw.pop("figsize", None))
    return fig, fig.subplots(nrows, ncols, **subplots_kw)


def plot_verification(rows, path: str | Path, *, title: str = "") -> Path:
    """VP gravity-module errors before and after compensation, per verification temperature (like seed 000's
    Fig. 6-7): one panel per temperature, dg in micro-g per position: uncompensated, method 1, method 2."""
    from .thermal import cluster_temperatures

    path = Path(path)
    temps = np.array([r.temp_c for r in rows])
    labels = cluster_temperatures(temps) if len(rows) else np.array([], int)
    n = int(labels.max() + 1) if len(rows) else 1
    fig, axes = new_figure(1, n, figsize=(4.2 * n, 3.6), squeeze=False, sharey=True)
    for c in range(n):
        ax = axes[0, c]
        sel = [r for r, lab in zip(rows, labels) if lab == c]
        if not sel:
            ax.text(0.5, 0.5, "no VP data", ha="center", transform=ax.transAxes)
            continue
        x = np.arange(len(sel))
        for key, lab, mk in (("dg_uncompensated_g", "uncompensated", "o-"), ("dg_method1_g", "method 1", "s-"),
                             ("dg_method2_g", "method 2", "^--")):
            ax.plot(x, [getattr(r, key) * 1e6 for r in sel], mk, label=lab, ms=4)
        lim = sel[0].tolerance_g * 1e6
        ax.axhspan(-lim, lim, color="0.9", zorder=0, label=f"tolerance +-{lim:.0f} ug")
        ax.set_xticks(x, [r.position for r in sel], fontsize=7, rotation=45)
        ax.set_title(f"{np.mean([r.temp_c for r in sel]):+.1f} C")
        ax.axhline(0, color="k", lw=0.5)
        if c == 0:
            ax.set_ylabel("dg = |a| - 1  [micro-g]")
    if rows:
        axes[0, 0].legend(fontsize=7)
    fig.suptitle(title or "Gravity-module error at the verification positions")
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=110)
    return path
