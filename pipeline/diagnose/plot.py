"""The figure of ``diagnose``: block residuals over time per axis, before and after, located windows shaded."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from pipeline.positions import AXES


def plot_residuals(path: str | Path, t_h: np.ndarray, before_v: np.ndarray, after_v: np.ndarray,
                   sigma_v: np.ndarray, windows_h: list[tuple[float, float]],
                   located_h: list[tuple[float, float]] = (), title: str = "") -> Path:
    """Write a PNG: one panel per axis with the block residuals (uV) against the passport (before) and the
    extended model (after), the +-3 sigma noise band of the blocks, the windows where the residual before exceeds
    the noise (located, marked under each panel) and where the findings show (shaded)."""
    from pipeline.plots import new_figure

    path = Path(path)
    fig, axes = new_figure(3, 1, figsize=(11, 8), sharex=True)
    for i, ax in enumerate(axes):
        for k, (a, b) in enumerate(windows_h):
            ax.axvspan(a, b, color="tab:orange", alpha=0.15, lw=0, label="where the findings show" if k == 0 else None)
        for k, (a, b) in enumerate(located_h):
            ax.axvspan(a, b, ymin=0.0, ymax=0.03, color="tab:red", lw=0,
                       label="located: residual beyond 5 sigma" if k == 0 else None)
        ax.fill_between(t_h, -3e6 * sigma_v[:, i], 3e6 * sigma_v[:, i], color="0.85", lw=0, step="mid",
                        label="3 sigma (noise)")
        ax.plot(t_h, before_v[:, i] * 1e6, ".", ms=2, color="tab:red", label="before (passport)")
        ax.plot(t_h, after_v[:, i] * 1e6, ".", ms=2, color="tab:blue", label="after (extended model)")
        ax.set_ylabel(f"residual {AXES[i]} (uV)")
        ax.grid(alpha=0.3)
    axes[0].legend(loc="upper right", fontsize=8, markerscale=4)
    axes[-1].set_xlabel("time since the start of the recording (h)")
    if title:
        axes[0].set_title(title, fontsize=10)
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=110)
    return path


__all__ = ["plot_residuals"]
