"""The calibration passport (docs/contract.md): one JSON document per version, and its typed form.

- :func:`build_passport` assembles the required content from a :class:`pipeline.calibrate.result.UnitFit` and its
  verification; the registry (``pipeline.passport.registry``) adds version, parent link, creation time and
  provenance.
- :class:`Passport`: the typed passport (format version, unit, method, constants, thermal model, rate terms,
  extended model, validity range), with the JSON document as stored beside it; :func:`load_passport` is the one
  loader (a document or a file), and :meth:`Passport.compensation_model` the right compensation model for every
  method: the thermal model (``tilt_six_position``, ``scalar``), the thermal model with rate terms and lag
  (``differential``: :class:`pipeline.thermal.DifferentialModel`), or the extended model a ``diagnose`` wrote
  (:class:`pipeline.effects.model.ExtendedModel`, which needs the samples' signal context).
- :func:`load_model` (the base thermal model), :func:`load_extended`, :func:`compensate_extended` and
  :func:`read_passport` (the document of a file) are views of the same loader.
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from pipeline.errors import ThermocalError
from pipeline.model import output_unit, specific_force_g
from pipeline.thermal import DifferentialModel, PolynomialModel, RateTerms, ThermalModel, thermal_model_from_dict
from pipeline.verify import summary_by_temperature

if TYPE_CHECKING:  # the extended model pulls in the effect catalogue (scipy.signal): imported where one is read
    from pipeline.effects.model import ExtendedModel

#: the passport's format version (its ``schema`` field)
SCHEMA_ID = "thermocal.passport/1"
#: the method of a passport that does not record one (written before methods were recorded)
DEFAULT_METHOD = "tilt_six_position"


def failed_verification(subject: str) -> str:
    """The one wording of a passport that failed its verification (``status`` fail), for any command that uses one
    (apply, export, diagnose, certificate, the differential base): ``AU-0001 v3 failed its verification (status
    fail): its compensated errors exceeded the limits``."""
    return f"{subject} failed its verification (status fail): its compensated errors exceeded the limits"


def gains_v_per_g(doc: dict) -> list[float] | None:
    """|K_ii| of the normal-temperature constants (output unit per g), for ppm of the gain and micro-g."""
    try:
        return [abs(float(doc["coefficients"]["K"][i][i])) for i in range(3)]
    except (KeyError, IndexError, TypeError, ValueError):
        return None


def output_unit_of(doc: dict) -> str:
    """The unit of the passport's outputs: its ``output_unit``, else (a passport written before it was recorded) the
    one its gains say (:func:`pipeline.model.output_unit`)."""
    if isinstance(doc.get("output_unit"), str) and doc["output_unit"]:
        return doc["output_unit"]
    gains = gains_v_per_g(doc)
    return output_unit(gains, float(doc.get("g_local_mps2") or 9.80665)) if gains else "V"


def build_passport(
    fit,
    verification_rows,
    status: str,
    *,
    g_local_mps2: float,
    plateaus: list[dict],
    method: str = "tilt_six_position",
    tolerances=None,
    extra: dict | None = None,
) -> dict:
    """Passport content (without version/parent/provenance, which the registry sets).

    ``method`` records the calibration method that made the passport: ``tilt_six_position`` (seed 000; the
    constants per plateau by the closed form or least squares, see ``per_plateau[].method``), ``scalar``,
    ``differential``. ``output_unit``: the unit the outputs were recorded in (:func:`pipeline.model.output_unit`),
    K being in that unit per g and U0 in that unit. ``tolerances`` (:class:`pipeline.verify.Tolerances`): the
    limits the verification judged with, stated as ``unit_grade`` and ``tolerances`` (physics.md "Unit grades").
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
        "output_unit": output_unit(np.abs(np.diag(np.asarray(model.K0, dtype=float))), g_local_mps2),
        "method": method,
        "coefficients": {"K": np.asarray(model.K0).tolist(), "U0": np.asarray(model.U00).tolist()},
        "per_plateau": [p.to_dict() for p in fit.per_plateau],
        "thermal_model": model.to_dict(),
        "plateaus": plateaus,
        "verification": [r.to_dict() for r in verification_rows],
        "verification_summary": summary_by_temperature(verification_rows),
        "status": status,
        **({"unit_grade": tolerances.grade, "tolerances": tolerances.to_dict()} if tolerances is not None else {}),
        "notes": list(fit.skipped),
        "valid_temp_c": list(fit.valid_temp_c) if getattr(fit, "valid_temp_c", None) else None,
        "uncertainty": uncertainty_block(fit),
    }
    if extra:
        doc.update(extra)
    return doc


def uncertainty_block(fit) -> dict | None:
    """The passport's ``uncertainty`` (docs/contract.md): standard uncertainties (1 sigma, same units) mirroring
    ``coefficients``, ``per_plateau`` and ``thermal_model`` (and, for the differential method, ``rate_terms``), with
    ``undetermined`` / ``fixed_by_convention`` naming the fields without a measured uncertainty and why, and
    ``basis`` what the numbers rest on; None where the fit has none."""
    from pipeline.uncertainty import as_json_list

    sigma = getattr(fit, "uncertainty", None)
    if sigma is None:
        return None
    tau = getattr(fit, "excess_scatter_v", None)
    basis = (
        sigma.basis
        if sigma.basis is not None
        else {
            "level": "standard uncertainty (1 sigma)",
            "segment_noise": "voltmeter noise measured in each static segment (std / sqrt(n)) and the readings' "
            "resolution q (q^2 / 12 where the noise does not dither it away)",
            "excess_scatter_v": as_json_list(tau) if tau is not None else None,
            "thermal_fit_birge_ratio": sigma.birge_ratio if sigma.dof else None,
            "thermal_fit_dof": sigma.dof,
        }
    )
    return {
        "coefficients": {"K": as_json_list(sigma.K0), "U0": as_json_list(sigma.U00)},
        "per_plateau": [
            {
                "temp_c": round(p.temp_c, 4),
                "run_id": p.run_id,
                "plateau": p.plateau,
                "K": as_json_list(p.K_sigma) if p.K_sigma is not None else None,
                "U0": as_json_list(p.U0_sigma) if p.U0_sigma is not None else None,
            }
            for p in fit.per_plateau
        ],
        "thermal_model": sigma.thermal_model,
        **(sigma.extra or {}),
        "basis": basis,
    }


@dataclass(frozen=True)
class Passport:
    """A passport, typed: what every layer past the registry reads of it (apply, diagnose, export, the figures,
    a method's base passport). ``format``: the format version (``thermocal.passport/1``); ``method``:
    ``tilt_six_position``, ``scalar``, ``differential`` (:mod:`pipeline.calibrate.methods`); ``K`` (3, 3) and
    ``U0`` (3,) at ``normal_temp_c`` (C) in the output unit ``output_unit`` (V or m/s^2: ``K`` per g);
    ``thermal_model`` K(T), U0(T); ``rate_terms`` the differential method's rate terms and lag (None for the
    others); ``extended`` the model a ``diagnose`` fitted (None: none); ``valid_temp_c`` the calibration
    temperatures the data covered (C) as stated; ``plateau_temps_c`` the calibration plateaus' temperatures (C);
    ``window_range_c`` the temperatures the differential method's orientation windows covered (C; None: none);
    ``uncertainty`` the standard uncertainties as stored (docs/contract.md; None: none); ``content_sha256`` and
    ``created_utc`` the registry's identity and time of the version (None before it is published); ``document``
    the JSON object as stored (docs/contract.md), unchanged: what the registry hashes, signs and writes."""

    format: str
    unit: str | None
    method: str
    version: int | None
    normal_temp_c: float
    g_local_mps2: float
    K: np.ndarray
    U0: np.ndarray
    thermal_model: ThermalModel
    rate_terms: RateTerms | None = None
    extended: ExtendedModel | None = None
    status: str | None = None
    valid_temp_c: tuple[float, float] | None = None
    output_unit: str = "V"
    plateau_temps_c: tuple[float, ...] = ()
    window_range_c: tuple[float, float] | None = None
    uncertainty: dict[str, Any] | None = field(default=None, repr=False, compare=False)
    content_sha256: str | None = None
    created_utc: str | None = None
    document: dict[str, Any] = field(default_factory=dict, repr=False, compare=False)

    @classmethod
    def from_dict(cls, doc: dict, path: str | None = None) -> Passport:
        """The typed passport of a JSON document; ThermocalError (one line, naming ``path``) when it is not a
        passport of this format or its constants or models cannot be read. Fields the models do not need may be
        absent (a document assembled in memory)."""
        if not isinstance(doc, dict):
            raise ThermocalError("a passport is a JSON object", path=path)
        fmt = doc.get("schema", SCHEMA_ID)
        if fmt != SCHEMA_ID:
            raise ThermocalError(f"not a {SCHEMA_ID} document (schema {fmt!r})", path=path)
        try:
            c = doc["coefficients"]
            K, U0 = np.asarray(c["K"], float), np.asarray(c["U0"], float)
            t0 = float(doc.get("normal_temp_c", 20.0))
            thermal = thermal_model_from_dict(doc["thermal_model"], K, U0, t0)
            rate = RateTerms.from_dict(doc["rate_terms"]) if doc.get("rate_terms") else None
            extended = load_extended(doc)
        except (KeyError, TypeError, ValueError, IndexError) as e:
            raise ThermocalError(f"passport cannot be read: {type(e).__name__}: {e}", path=path) from None
        if K.shape != (3, 3) or U0.shape != (3,):
            raise ThermocalError("passport coefficients: K must be 3x3 and U0 a 3-vector", path=path)
        if rate is not None and not isinstance(thermal, PolynomialModel):
            raise ThermocalError("passport with rate terms needs a polynomial thermal model", path=path)
        valid = doc.get("valid_temp_c")
        windows = (doc.get("differential") or {}).get("windows") or []
        return cls(
            format=fmt,
            unit=doc.get("unit"),
            method=doc.get("method") or DEFAULT_METHOD,
            version=doc.get("version"),
            normal_temp_c=t0,
            g_local_mps2=float(doc.get("g_local_mps2", 9.80665)),
            K=K,
            U0=U0,
            thermal_model=thermal,
            rate_terms=rate,
            extended=extended,
            status=doc.get("status"),
            valid_temp_c=_range_of(valid),
            output_unit=output_unit_of(doc),
            plateau_temps_c=tuple(
                float(p["temp_c"])
                for p in doc.get("per_plateau") or []
                if isinstance(p, dict) and isinstance(p.get("temp_c"), (int, float))
            ),
            window_range_c=(
                (min(float(w["temp_min_c"]) for w in windows), max(float(w["temp_max_c"]) for w in windows))
                if windows
                else None
            ),
            uncertainty=doc.get("uncertainty"),
            content_sha256=doc.get("content_sha256"),
            created_utc=doc.get("created_utc"),
            document=doc,
        )

    def to_dict(self) -> dict[str, Any]:
        """The JSON document (docs/contract.md), as it was loaded."""
        return self.document

    @property
    def valid_range_c(self) -> tuple[float, float] | None:
        """The temperature range (C) the passport's data covered: ``valid_temp_c``; for a passport written before
        that field, the span of its calibration plateaus, else of its differential orientation windows; None when
        it states none."""
        if self.valid_temp_c is not None:
            return self.valid_temp_c
        if self.plateau_temps_c:
            return min(self.plateau_temps_c), max(self.plateau_temps_c)
        return self.window_range_c

    def compensation_model(self):
        """The model that compensates this passport's unit: the extended model when a ``diagnose`` wrote one
        (its compensation needs the signal context: :func:`compensate_extended`), else the thermal model with the
        rate terms and lag when the method fitted them (:class:`pipeline.thermal.DifferentialModel`), else the
        thermal model (:class:`pipeline.thermal.PolynomialModel` or ``PiecewiseModel``). All but the extended model
        give ``constants_at(temp_c)`` for ``pipeline.compensate``."""
        if self.extended is not None:
            return self.extended
        if self.rate_terms is not None:
            return DifferentialModel(self.thermal_model, self.rate_terms)
        return self.thermal_model


def _range_of(v) -> tuple[float, float] | None:
    """A stated [lo, hi] range of two numbers as a tuple; None otherwise."""
    if isinstance(v, (list, tuple)) and len(v) == 2 and all(isinstance(x, (int, float)) for x in v):
        return float(v[0]), float(v[1])
    return None


def load_passport(source: Passport | dict | str | Path) -> Passport:
    """The one passport loader: a JSON document (dict) or a passport file (a :class:`Passport` is returned as it
    is); ThermocalError naming the file when it cannot be read or is not a passport."""
    if isinstance(source, Passport):
        return source
    if isinstance(source, dict):
        return Passport.from_dict(source)
    try:
        doc = json.loads(Path(source).read_bytes())
    except OSError as e:
        raise ThermocalError(f"cannot read passport ({e.strerror or e})", path=str(source)) from None
    except UnicodeDecodeError:
        raise ThermocalError("not a passport: the file is not JSON text", path=str(source)) from None
    except ValueError as e:
        raise ThermocalError(f"not a passport: the file is not JSON ({e})", path=str(source)) from None
    if not isinstance(doc, dict) or doc.get("schema") != SCHEMA_ID:
        raise ThermocalError(f"not a {SCHEMA_ID} document", path=str(source))
    return Passport.from_dict(doc, path=str(source))


def read_passport(path: str | Path) -> dict:
    """The JSON document of a passport file (checked by :func:`load_passport`)."""
    return load_passport(path).to_dict()


def load_model(passport: Passport | dict) -> ThermalModel:
    """The passport's constants and base thermal model (with K0, U00, deltas, constants_at), for
    ``pipeline.compensate``: :attr:`Passport.thermal_model`. The rate terms and an extended model are left out;
    :meth:`Passport.compensation_model` gives them."""
    return load_passport(passport).thermal_model


def load_extended(document: dict) -> ExtendedModel | None:
    """The extended model (written by ``diagnose``) of a passport document, or None when it has none."""
    d = document.get("extended_model")
    if d is None:
        return None
    from pipeline.effects.model import ExtendedModel

    return ExtendedModel.from_dict(d)


def compensate_extended(
    passport: Passport | dict, u_v: np.ndarray, ctx, element_temp_c: np.ndarray | None = None
) -> np.ndarray:
    """Specific force (n, 3) g of outputs ``u_v`` (n, 3) V with the passport's extended model, falling back to
    method 1 with the passport's own thermal model when it has none.

    ``ctx`` (:class:`pipeline.effects.base.SignalContext`) describes the samples: ``t_s`` (s since the recording
    started), ``temp_c`` (thermosensor, C), ``ramp_sign``, ``move_start_s`` / ``arrive_s`` and ``position_idx``;
    its ``a_g`` and ``constants`` are not used. With thermal lag, ``element_temp_c`` may give the lagged temperature
    computed on a continuous thermosensor series when the samples have gaps (default: the lag of ``ctx.temp_c``
    over ``ctx.t_s``).
    """
    ext = passport.extended if isinstance(passport, Passport) else load_extended(passport)
    if ext is not None:
        return ext.specific_force_g(u_v, ctx, element_temp_c)
    k, u0 = load_model(passport).constants_at(np.asarray(ctx.temp_c, float))
    return specific_force_g(k, u0, np.asarray(u_v, float))
