"""What every command of the ``thermocal`` command line shares: the typer apps (``app``, its groups
``passport_app`` and ``server_app``), the help texts and option types used by several commands (``JsonFlag``), the
output of a result (:func:`emit`) and the calibration options' checks (:func:`calibration_settings`,
:func:`check_method`). A command module imports from here; nothing here imports a command module.
"""

from __future__ import annotations

import json
import sys
from typing import Annotated

import typer
import typer.core

from pipeline.calibrate.methods import names as method_names
from pipeline.errors import ThermocalError
from pipeline.jsonable import json_default

#: The words help shows for an option's value (by its Python type), where typer shows type tags (``<float>``,
#: ``<list[Path]>``); an option's ``metavar`` wins.
_VALUE_WORDS = {"float": "NUMBER", "int": "INTEGER", "str": "TEXT", "Path": "PATH"}


class PlainCommand(typer.core.TyperCommand):
    """A command whose help is in plain words: an argument by its name (``RUN``, ``[V]``, ``RUN...`` in the usage
    line, where typer writes ``{RUN}``, which reads as a set of choices), an option's value as a word (``PATH``,
    ``NUMBER``, its ``metavar``), a flag alone. Through click's public hooks (``collect_usage_pieces``,
    ``format_options``) and each parameter's own help text (``get_help_record``)."""

    def collect_usage_pieces(self, ctx) -> list[str]:
        pieces = [self.options_metavar] if self.options_metavar else []
        return pieces + [_name(p) for p in self.get_params(ctx) if p.param_type_name == "argument"]

    def format_options(self, ctx, formatter) -> None:
        sections: dict[str, list[tuple[str, str]]] = {"Arguments": [], "Options": []}
        for p in self.get_params(ctx):
            record = p.get_help_record(ctx)
            if record is not None:
                sections["Arguments" if p.param_type_name == "argument" else "Options"].append((_name(p), record[1]))
        for title, rows in sections.items():
            if rows:
                with formatter.section(title):
                    formatter.write_dl(rows)


def _name(p) -> str:
    """A parameter as help shows it: ``RUN``/``[V]``/``RUN...``; ``--out PATH``; ``--figures / --no-figures``."""
    if p.param_type_name == "argument":
        name = p.metavar or p.name.upper()
        return (name if p.required else f"[{name}]") + ("..." if p.nargs != 1 else "")
    names = ", ".join(p.opts)
    if not p.is_flag:
        names += " " + (p.metavar or _VALUE_WORDS.get(p.bare_type().removeprefix("list[").removesuffix("]"), "VALUE"))
    return names + "".join(f" / {o}" for o in p.secondary_opts)


class PlainTyper(typer.Typer):
    """typer's app whose commands are :class:`PlainCommand` and whose help is plain text (no boxes)."""

    def __init__(self, **kwargs):
        super().__init__(rich_markup_mode=None, context_settings={"max_content_width": 120}, **kwargs)

    def command(self, *args, **kwargs):
        return super().command(*args, cls=kwargs.pop("cls", PlainCommand), **kwargs)


app = PlainTyper(
    add_completion=False,
    pretty_exceptions_enable=False,
    help="thermocal: thermal-chamber calibration of accelerometer units.",
)
passport_app = PlainTyper(help="The passport audit trail: log, show, diff, approve, verify, head.")
app.add_typer(passport_app, name="passport")
server_app = PlainTyper(no_args_is_help=True, help="thermocal's local Prefect server: where flow runs are recorded.")
app.add_typer(server_app, name="server")

#: The help texts of options and arguments that several commands share.
JSON_HELP = "print one JSON object on stdout instead of text"
REGISTRY_HELP = "registry folder: every unit's passport versions"
UNIT_HELP = "the unit's serial number, e.g. AU-0001"

#: ``--json``, the flag of every command that can print its result as one JSON object: ``as_json: JsonFlag = False``
JsonFlag = Annotated[bool, typer.Option("--json", help=JSON_HELP)]
#: ``--grade`` of calibrate, fleet and serve (physics.md "Unit grades"): ``grade: GradeOption = None``
GradeOption = Annotated[
    str | None,
    typer.Option(
        "--grade",
        help="the unit's grade, which sets the verification limits of |dg| at T0 and over the range: navigation "
        "| tactical | industrial | consumer (default: the run's unit_grade, else navigation; the output states "
        "the limits)",
    ),
]


def _version() -> str:
    from importlib.metadata import PackageNotFoundError, version

    try:
        return version("thermocal")
    except PackageNotFoundError:  # a source tree that was not installed
        return "unknown"


def _print_version(value: bool) -> None:
    if value:
        sys.stdout.write(f"thermocal {_version()}\n")
        raise typer.Exit(0)


@app.callback()
def _main_options(
    _version_flag: bool = typer.Option(
        False, "--version", callback=_print_version, is_eager=True, help="print the version of thermocal and exit"
    ),
):
    """thermocal: thermal-chamber calibration of accelerometer units."""


def emit(obj, as_json: bool, text: str | None = None) -> None:
    """A command's result on stdout: ``obj`` as one JSON object with ``as_json``, else ``text`` (``obj`` as JSON
    when there is no text)."""
    if as_json:
        sys.stdout.write(json.dumps(obj, indent=2, default=json_default) + "\n")
    else:
        sys.stdout.write((text if text is not None else json.dumps(obj, indent=2, default=json_default)) + "\n")
    sys.stdout.flush()


def check_method(method: str) -> None:
    """``--method``: auto or a method of the registry (:mod:`pipeline.calibrate.methods`, by name: none is
    imported)."""
    if method != "auto" and method not in method_names():
        raise ThermocalError(f"unknown method {method!r} (auto, {', '.join(method_names())})", where="--method")


def needs_base(method: str) -> bool:
    """Whether ``method`` starts from a base passport (``--base-passport``)."""
    from pipeline.calibrate.methods import by_name

    return by_name(method).uses_base_passport


def calibration_settings(
    thermal_model: str,
    constants_method: str,
    tol_normal_g: float | None,
    tol_range_g: float | None,
    grade: str | None = None,
):
    """The settings of calibrate, fleet and serve from their options, each checked (a one-line error naming it).
    ``grade`` None: the run's ``unit_grade``; ``tol_normal_g`` / ``tol_range_g`` None: the grade's limits."""
    from pipeline.calibrate.settings import CalibrationSettings
    from pipeline.constants import CONSTANTS_METHODS
    from pipeline.thermal import THERMAL_MODELS
    from pipeline.verify import GRADES

    if thermal_model not in THERMAL_MODELS:
        raise ThermocalError(
            f"unknown thermal model {thermal_model!r} ({', '.join(THERMAL_MODELS[1:])})", where="--thermal-model"
        )
    if constants_method not in CONSTANTS_METHODS:
        raise ThermocalError(
            f"unknown constants method {constants_method!r} ({', '.join(CONSTANTS_METHODS)})",
            where="--constants-method",
        )
    if grade is not None and grade not in GRADES:
        raise ThermocalError(f"unknown unit grade {grade!r} ({', '.join(GRADES)})", where="--grade")
    for flag, value in (("--tol-normal-g", tol_normal_g), ("--tol-range-g", tol_range_g)):
        if value is not None and not value > 0:
            raise ThermocalError(f"a limit must be a positive number of g, got {value:g}", where=flag)
    return CalibrationSettings(
        thermal_model=thermal_model,
        constants_method=constants_method,
        grade=grade,
        tol_normal_g=tol_normal_g,
        tol_range_g=tol_range_g,
    )
