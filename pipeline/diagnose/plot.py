"""The figure of ``diagnose``: the AU temperature over time, and the block residuals over time per axis before and
after, with the windows of each finding shaded in a colour of its own."""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

import numpy as np

from pipeline.model import OUTPUT_UNITS
from pipeline.positions import AXES

#: Colours of the findings, most important first (matplotlib's qualitative "tab" colours, red and blue left to the
#: residual series).
_FINDING_COLOURS = (
    "tab:orange",
    "tab:green",
    "tab:purple",
    "tab:brown",
    "tab:pink",
    "tab:olive",
    "tab:cyan",
    "tab:gray",
)


def plot_residuals(
    path: str | Path,
    t_h: np.ndarray,
    before_v: np.ndarray,
    after_v: np.ndarray,
    sigma_v: np.ndarray,
    windows_h: list[tuple[float, float]],
    located_h: Sequence[tuple[float, float]] = (),
    title: str = "",
    *,
    findings: list[tuple[str, list[tuple[float, float]]]] | None = None,
    temperature: tuple[np.ndarray, np.ndarray] | None = None,
    output_unit: str = "V",
) -> Path:
    """Write a PNG: the AU temperature (C) over time when ``temperature`` = (hours, C) is given; one panel per axis
    with the block residuals (uV; mm/s^2 when ``output_unit`` is m/s^2) against the passport (before) and the
    extended model (after), the +-3 sigma noise band of the blocks and the windows where the residual before
    exceeds the noise (located, marked under each panel). ``findings``: (name, windows in hours) per finding, each in
    its own colour and lane (a band of the top panel, a strip along the top of each residual panel); without it,
    ``windows_h`` (all findings together) are marked in one colour."""
    from pipeline.plots import new_figure

    path = Path(path)
    small, scale = OUTPUT_UNITS.get(output_unit, OUTPUT_UNITS["V"])
    shaded = findings if findings is not None else ([("where the findings show", list(windows_h))] if windows_h else [])
    n_top = 1 if temperature is not None else 0
    fig, axes = new_figure(
        3 + n_top,
        1,
        figsize=(11, 8 + 1.8 * n_top),
        sharex=True,
        gridspec_kw={"height_ratios": [1.6] * n_top + [2.2] * 3},
    )
    if temperature is not None:
        tax = axes[0]
        tax.plot(temperature[0], temperature[1], "-", color="k", lw=1, label="AU temperature")
        tax.set_ylabel("AU temperature (C)")
        tax.grid(alpha=0.3)
    # each finding in a lane of its own, so that findings that overlap in time stay apart: a horizontal band of
    # the top panel, a strip along the top edge of each residual panel
    lane = 1.0 / max(len(shaded), 1)
    for k, (name, wins) in enumerate(shaded):
        colour = _FINDING_COLOURS[k % len(_FINDING_COLOURS)]
        for ax in axes:
            top = ax is axes[0] and n_top
            lo, hi = (1 - (k + 1) * lane, 1 - k * lane) if top else (0.97 - 0.04 * (k + 1), 0.97 - 0.04 * k)
            for j, (a, b) in enumerate(wins):
                ax.axvspan(
                    a,
                    b,
                    ymin=lo,
                    ymax=hi,
                    color=colour,
                    alpha=0.35 if top else 0.9,
                    lw=0,
                    label=f"{k + 1}. {name}" if (j == 0 and ax is axes[0]) else None,
                )
    for i, ax in enumerate(axes[n_top:]):
        for k, (a, b) in enumerate(located_h):
            ax.axvspan(
                a,
                b,
                ymin=0.0,
                ymax=0.03,
                color="tab:red",
                lw=0,
                label="located: residual beyond 5 sigma" if k == 0 else None,
            )
        ax.fill_between(
            t_h,
            -3 * scale * sigma_v[:, i],
            3 * scale * sigma_v[:, i],
            color="0.85",
            lw=0,
            step="mid",
            label="3 sigma (noise)",
        )
        ax.plot(t_h, before_v[:, i] * scale, ".", ms=2, color="tab:red", label="before (passport)")
        ax.plot(t_h, after_v[:, i] * scale, ".", ms=2, color="tab:blue", label="after (extended model)")
        ax.set_ylabel(f"residual {AXES[i]} ({small})")
        ax.grid(alpha=0.3)
    if shaded or n_top:
        axes[0].legend(
            loc="lower left", bbox_to_anchor=(0, 1.0), fontsize=8, frameon=False, ncols=min(len(shaded) + n_top, 4)
        )
    axes[n_top].legend(*_series_handles(axes[n_top]), loc="upper right", fontsize=8, markerscale=4)
    axes[-1].set_xlabel("time since the start of the recording (h)")
    if title:
        fig.suptitle(title, fontsize=10)
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=110)
    return path


def _series_handles(ax):
    """The residual panel's legend entries without the findings' shading (those have their own legend)."""
    handles, labels = ax.get_legend_handles_labels()
    keep = [(h, lab) for h, lab in zip(handles, labels) if not lab[:1].isdigit()]
    return [h for h, _ in keep], [lab for _, lab in keep]


def plot_diagnosis(path: str | Path, diagnosis, run, title: str = "", *, output_unit: str = "V") -> Path:
    """The figure of :func:`pipeline.diagnose.diagnosis.diagnose_run`'s result ``diagnosis`` on ``run``: the AU
    temperature trace on top, one colour per finding (in the report's order). Times are hours since the first
    voltmeter sample, as the block times of the diagnosis."""
    t0_ns = int(run.voltmeter["t_ns"].min())
    temp = run.au_temperature
    t_temp_h = (temp["t_ns"].to_numpy() - t0_ns) / 3.6e12
    findings = [
        (f["effect"], [((a - t0_ns) / 3.6e12, (b - t0_ns) / 3.6e12) for a, b in f["where"]["windows"]])
        for f in diagnosis.report["findings"]
    ]
    return plot_residuals(
        path,
        diagnosis.t_h,
        diagnosis.before_v,
        diagnosis.after_v,
        diagnosis.sigma_v,
        diagnosis.windows_h,
        diagnosis.located_h,
        title,
        findings=findings,
        temperature=(t_temp_h, temp["temp_c"].to_numpy()),
        output_unit=output_unit,
    )


__all__ = ["plot_diagnosis", "plot_residuals"]
