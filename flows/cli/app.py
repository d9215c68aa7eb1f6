"""What every command of the ``thermocal`` command line shares: the typer apps (``app``, its groups
``passport_app`` and ``server_app``), the help texts and option types used by several commands (``JsonFlag``), the
output of a result (:func:`emit`) and the calibration options' checks (:func:`calibration_settings`,
:func:`check_method`). A command module imports from here; nothing here imports a command module.
"""

from __future__ import annotations

import json
import sys
from pathlib import Path
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
UNVERIFIED_HELP = (
    "use a passport that does not verify (altered, unsigned, signed by a key this station does not trust, not "
    "canonical) or a loose file's; every output says UNVERIFIED"
)
#: ``--unverified`` of every command that uses a passport (apply, export, report, diagnose)
UnverifiedFlag = Annotated[bool, typer.Option("--unverified", help=UNVERIFIED_HELP)]
#: the help of the UNIT argument of a command that also takes a passport file instead (export, report)
UNIT_OR_FILE_HELP = (
    "the unit's serial number (with --registry), or a passport file (a version file of a registry is checked "
    "against its registry)"
)


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
    """A command's result on stdout: ``obj`` as one JSON object with ``as_json`` (control characters escaped by
    JSON), else ``text`` with its control characters escaped (:func:`pipeline.words.printable`; ``obj`` as JSON
    when there is no text)."""
    from pipeline.words import printable

    if as_json:
        sys.stdout.write(json.dumps(obj, indent=2, default=json_default) + "\n")
    else:
        sys.stdout.write(
            printable(text if text is not None else json.dumps(obj, indent=2, default=json_default)) + "\n"
        )
    sys.stdout.flush()


def warn(text: str) -> None:
    """One warning line on stderr (``thermocal: warning: ...``), control characters escaped."""
    from pipeline.words import printable

    print(f"thermocal: warning: {printable(text, lines=False)}", file=sys.stderr)


def passport_in_use(unit_or_file: str, version: int | None, registry: Path | None, unverified: bool):
    """The passport a command uses and its :class:`pipeline.passport.registry.VersionState`, verified (the one path:
    :meth:`pipeline.passport.registry.Registry.load_state`, or
    :func:`pipeline.passport.registry.load_passport_file` for a passport file when no ``--registry`` is given).
    Refused in one line when it does not verify, unless ``unverified``."""
    from pipeline.passport.registry import Registry, load_passport_file

    if registry is not None:
        return Registry(registry).load_state(unit_or_file, version, unverified=unverified)
    path = Path(unit_or_file)
    if not path.is_file():
        raise ThermocalError(
            "no such passport file (give a unit's serial with --registry DIR, or a passport file)", path=str(path)
        )
    if version is not None:
        raise ThermocalError("a version number goes with a unit and --registry, not with a passport file", where="V")
    return load_passport_file(path, unverified=unverified)


def refuse_out_over_inputs(out: Path, inputs: list[Path], registry: Path | None = None) -> None:
    """An output file (``--out``) that would replace what the command reads (``inputs``: the passport file, the
    run, a folder holding them) or a registry's record (a file of a unit's folder ``REG/units/UNIT/``: its signed
    versions and log; anything under ``registry``'s ``units``): refused in one line before anything is written."""
    target = out.resolve()
    for src in inputs:
        s = Path(src).resolve()
        if target == s or (s.is_dir() and target.is_relative_to(s)):
            raise ThermocalError(f"{out} would replace the input {src}: write the output elsewhere", where="--out")
    folder = target.parent
    in_unit_folder = folder.parent.name == "units" and (folder / "log.jsonl").is_file()
    if in_unit_folder or (registry is not None and target.is_relative_to(Path(registry).resolve() / "units")):
        raise ThermocalError(
            f"{out} is inside a registry's unit folder, which holds only its signed records: write the output "
            "elsewhere",
            where="--out",
        )


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
