"""The calibration passport (contract.md): one JSON document per version.

``build_passport`` assembles the required content from a :class:`pipeline.calibrate.tilt.UnitFit` and its
verification; the registry (``pipeline.passport.registry``) adds version, parent link, creation time and provenance.
``load_model`` turns a passport back into a :class:`pipeline.model.ConstantsModel` for compensation.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from pipeline.thermal import thermal_model_from_dict
from pipeline.verify import summary_by_temperature

SCHEMA_ID = "thermocal.passport/1"


def build_passport(fit, verification_rows, status: str, *, g_local_mps2: float, plateaus: list[dict],
                   method: str = "tilt_six_position", extra: dict | None = None) -> dict:
    """Passport content (without version/parent/provenance, which the registry sets).

    ``method`` records the calibration method that made the passport: ``tilt_six_position`` (seed 000; the
    constants per plateau by the closed form or least squares, see ``per_plateau[].method``), ``scalar``,
    ``differential``.
    """
    model = fit.model
    doc = {
        "schema": SCHEMA_ID,
        "unit": fit.unit,
        "version": None,
        "parent_sha256": None,
        "created_utc": None,
        "normal_temp_c": float(fit.normal_temp_c),
        "g_local_mps2": float(g_local_mps2),
        "method": method,
        "coefficients": {"K": np.asarray(model.K0).tolist(), "U0": np.asarray(model.U00).tolist()},
        "per_plateau": [p.to_dict() for p in fit.per_plateau],
        "thermal_model": model.to_dict(),
        "plateaus": plateaus,
        "verification": [r.to_dict() for r in verification_rows],
        "verification_summary": summary_by_temperature(verification_rows),
        "status": status,
        "notes": list(fit.skipped),
        "valid_temp_c": list(fit.valid_temp_c) if getattr(fit, "valid_temp_c", None) else None,
        "uncertainty": uncertainty_block(fit),
    }
    if extra:
        doc.update(extra)
    return doc


def uncertainty_block(fit) -> dict | None:
    """The passport's ``uncertainty`` (contract.md): standard uncertainties (1 sigma, same units) mirroring
    ``coefficients``, ``per_plateau`` and ``thermal_model``; None where the fit has none."""
    from pipeline.uncertainty import as_json_list

    sigma = getattr(fit, "uncertainty", None)
    if sigma is None:
        return None
    tau = getattr(fit, "excess_scatter_v", None)
    return {
        "coefficients": {"K": as_json_list(sigma.K0), "U0": as_json_list(sigma.U00)},
        "per_plateau": [{"temp_c": round(p.temp_c, 4), "run_id": p.run_id, "plateau": p.plateau,
                         "K": as_json_list(p.K_sigma) if p.K_sigma is not None else None,
                         "U0": as_json_list(p.U0_sigma) if p.U0_sigma is not None else None}
                        for p in fit.per_plateau],
        "thermal_model": sigma.thermal_model,
        "basis": {"level": "standard uncertainty (1 sigma)",
                  "segment_noise": "voltmeter noise measured in each static segment (std / sqrt(n))",
                  "excess_scatter_v": as_json_list(tau) if tau is not None else None,
                  "thermal_fit_birge_ratio": sigma.birge_ratio if sigma.dof else None,
                  "thermal_fit_dof": sigma.dof},
    }


def load_model(passport: dict):
    """The passport's constants and thermal model as a ConstantsModel (with K0, U00, deltas, constants_at).

    A passport extended by ``diagnose`` (``extended_model``) is evaluated by the effects of ``pipeline.effects``
    where compensation of the extra terms needs the signal context; here it is the base model.
    """
    c = passport["coefficients"]
    return thermal_model_from_dict(passport["thermal_model"], np.asarray(c["K"], float), np.asarray(c["U0"], float),
                                   float(passport.get("normal_temp_c", 20.0)))


def read_passport(path: str | Path) -> dict:
    from pipeline.errors import ThermocalError

    try:
        doc = json.loads(Path(path).read_text())
    except (OSError, ValueError) as e:
        raise ThermocalError(f"cannot read passport: {e}", path=str(path)) from None
    if not isinstance(doc, dict) or doc.get("schema") != SCHEMA_ID:
        raise ThermocalError(f"not a {SCHEMA_ID} document", path=str(path))
    return doc
