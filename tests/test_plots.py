"""The verification figure beside each passport: one axes with a panel per VP temperature, drawn straight to PNG."""

from __future__ import annotations

import numpy as np
from PIL import Image

from pipeline import plots
from pipeline.verify import VerificationRow


def _row(temp_c: float, position: str, dg_ug: float, tol_ug: float = 1000.0) -> VerificationRow:
    return VerificationRow(temp_c=temp_c, position=position, run_id="r", t_start_ns=0, t_end_ns=1,
                           dg_uncompensated_g=dg_ug * 1e-6, dg_method1_g=0.1 * dg_ug * 1e-6,
                           dg_method2_g=0.2 * dg_ug * 1e-6, dg_method2_simplified_g=0.0, tolerance_g=tol_ug * 1e-6,
                           passed=True)


def test_panels_by_temperature_coldest_first():
    """Rows in time order (+45, then -10, then one VP at +70, then +44.6 again) give three panels, coldest first,
    each at least four slots wide with its points centred, one empty slot between panels."""
    rows = ([_row(45.0, f"VP{k}", 100.0 * k) for k in range(1, 7)] + [_row(-10.0, f"VP{k}", -50.0) for k in (1, 2)]
            + [_row(70.2, "VP6", 3.0)] + [_row(44.6, "VP1", 7.0)])
    panels = plots._panels(rows)
    assert [round(p["temp_c"], 1) for p in panels] == [-10.0, 44.9, 70.2]
    assert [[r.position for r in p["rows"]] for p in panels] == [["VP1", "VP2"],
                                                                   [f"VP{k}" for k in range(1, 7)] + ["VP1"],
                                                                   ["VP6"]]
    assert [p["width"] for p in panels] == [4, 7, 4]
    assert [p["x0"] for p in panels] == [0.0, 5.0, 13.0]
    np.testing.assert_allclose(panels[0]["x"], [1.5, 2.5])   # two points centred in four slots
    np.testing.assert_allclose(panels[2]["x"], [15.0])
    for p in panels:
        assert p["x0"] < p["x"].min() and p["x"].max() < p["x0"] + p["width"]
    assert plots._panels([]) == []


def test_png_size_follows_the_positions_and_the_lines_are_drawn(tmp_path):
    rows = [_row(t, f"VP{k}", 500.0 * (k - 3), tol) for t, tol in ((-10.0, 1000.0), (20.0, 300.0), (45.0, 1000.0))
            for k in range(1, 7)]
    path = plots.plot_verification(rows, tmp_path / "sub" / "v0001.png", title="AU-0001 v1")
    img = np.asarray(Image.open(path).convert("RGB"))
    slots = 3 * 6 + 2
    width_in = plots._MARGINS_IN["left"] + plots._MARGINS_IN["right"] + plots._SLOT_IN * slots
    assert img.shape[:2] == (round(plots._HEIGHT_IN * plots._VERIFICATION_DPI),
                             round(width_in * plots._VERIFICATION_DPI))
    blue = np.all(np.abs(img.astype(int) - [0x1F, 0x77, 0xB4]) < 30, axis=-1)  # the uncompensated series (C0)
    assert blue.sum() > 500
    grey = np.all(np.abs(img.astype(int) - 230) <= 1, axis=-1)  # the tolerance bands (colour 0.9)
    assert grey.sum() > 5000
    empty = plots.plot_verification([], tmp_path / "empty.png")
    assert Image.open(empty).size[0] == round((plots._MARGINS_IN["left"] + plots._MARGINS_IN["right"]
                                               + plots._SLOT_IN * plots._MIN_SLOTS) * plots._VERIFICATION_DPI)
