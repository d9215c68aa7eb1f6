"""The figures beside a published passport (its VP errors, its constants against temperature): what to draw
(:class:`FigureJob`) and drawing it under a temporary name (:func:`figure_beside`), inline by
:func:`pipeline.calibrate.publish.publish` or in a figure worker (:mod:`pipeline.calibrate.figure_worker`). Imports
neither the plotting code nor the passport's until a figure is drawn, so a worker starts with the plotting code
only."""

from __future__ import annotations

import contextlib
import os
from dataclasses import dataclass
from pathlib import Path

from pipeline.errors import ThermocalError


@dataclass(frozen=True)
class FigureJob:
    """A figure beside a published passport: ``path`` (``<passport>.png``, the VP errors of ``rows``; or
    ``<passport>.constants.png``, the constants of the ``passport`` at that path) and the start of its title (unit
    and version). Picklable, for :func:`draw_figure` in another process."""

    path: str
    kind: str  # "verification" | "constants"
    title: str
    rows: tuple = ()
    passport: str = ""

    def draw(self, tmp: Path) -> None:
        from pipeline.passport.document import load_passport
        from pipeline.plots import plot_constants, plot_verification

        if self.kind == "verification":
            plot_verification(list(self.rows), tmp, title=f"{self.title}: VP gravity-module error")
        else:
            plot_constants(
                load_passport(Path(self.passport)),
                tmp,
                title=f"{self.title}: constants per plateau against temperature, thermal model and residuals",
            )


def draw_figure(job: FigureJob) -> str | None:
    """Draw ``job``'s figure (as :func:`pipeline.calibrate.publish.publish` does for a new version); its path, or
    None when it was not made."""
    return figure_beside(Path(job.path), True, True, job.draw)


def drop_missing_figures(result: dict) -> dict:
    """``result`` (:func:`pipeline.calibrate.publish.publish`'s, with ``draw``) without the figure paths whose
    figures were not made."""
    for key in ("figure", "constants_figure"):
        if result.get(key) and not Path(result[key]).exists():
            result[key] = None
    return result


def figure_beside(path: Path, wanted: bool, redraw: bool, draw) -> str | None:
    """Draw a figure beside a passport with ``draw(tmp_path)`` when ``wanted``, for a new version (``redraw``) or
    where it is missing; its path, or None when there is none. Drawn under a temporary name, then renamed: a killed
    writer or a full disk leaves no partial figure (a leftover ".tmp-" file is removed by the registry at the unit's
    next publish)."""
    if wanted and (redraw or not path.exists()):
        tmp = path.with_name(f".tmp-{path.stem}-{os.getpid()}.png")
        try:
            draw(tmp)
            os.replace(tmp, path)
        except (OSError, ValueError, KeyError, ThermocalError):
            pass  # a figure is a convenience; the passport is written
        finally:
            with contextlib.suppress(OSError):
                tmp.unlink(missing_ok=True)
    return str(path) if path.exists() else None
