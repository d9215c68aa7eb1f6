"""The diagnose figure: the AU temperature trace on top, each finding in a colour and lane of its own."""

from __future__ import annotations

import numpy as np
from PIL import Image

from pipeline.diagnose.plot import _FINDING_COLOURS, plot_residuals


def _mask(img: np.ndarray, colour: str) -> np.ndarray:
    from matplotlib.colors import to_rgb

    rgb = 0.9 * np.array(to_rgb(colour)) * 255 + 0.1 * 255  # the strips' alpha over the white axes
    return np.all(np.abs(img.astype(float) - rgb) < 12, axis=-1)


def test_temperature_trace_and_a_colour_per_finding(tmp_path):
    t_h = np.linspace(0, 3, 300)
    before = np.column_stack([np.sin(t_h), np.cos(t_h), t_h]) * 1e-5
    after = before * 0.05
    sigma = np.full_like(before, 1e-6)
    findings = [("scale_nonlinearity", [(0.2, 1.0), (1.5, 2.0)]), ("time_drift", [(0.8, 1.2)])]
    temp = (np.linspace(0, 3, 50), np.interp(np.linspace(0, 3, 50), [0, 1, 2, 3], [20, -40, 70, 20]))
    path = plot_residuals(
        tmp_path / "d.png", t_h, before, after, sigma, [], [], "title", findings=findings, temperature=temp
    )
    img = np.asarray(Image.open(path).convert("RGB"))
    h = img.shape[0]
    top = img[: int(0.25 * h)]
    assert np.all(img[..., :3] < 40, axis=-1)[: int(0.25 * h)].sum() > 300  # the black temperature trace
    first, second = _mask(img, _FINDING_COLOURS[0]), _mask(img, _FINDING_COLOURS[1])
    assert first.sum() > 1000 and second.sum() > 300  # the residual panels' strips
    # the lanes do not share pixels: where the two findings overlap in time (0.8 .. 1.0 h) both colours show
    cols_first, cols_second = np.flatnonzero(first.any(axis=0)), np.flatnonzero(second.any(axis=0))
    assert np.intersect1d(cols_first, cols_second).size > 5
    plain = plot_residuals(tmp_path / "p.png", t_h, before, after, sigma, [(0.5, 1.0)], [(0.5, 0.6)])
    assert Image.open(plain).size[1] < h  # no temperature panel without it
    assert top.shape[0] > 0
