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

from pipeline.calibrate.methods import names as method_names
from pipeline.errors import ThermocalError
from pipeline.jsonable import json_default

app = typer.Typer(
    add_completion=False,
    pretty_exceptions_enable=False,
    help="thermocal: thermal-chamber calibration of accelerometer units.",
)
passport_app = typer.Typer(help="The passport audit trail: log, show, diff, approve, verify, head.")
app.add_typer(passport_app, name="passport")
server_app = typer.Typer(no_args_is_help=True, help="thermocal's local Prefect server: where flow runs are recorded.")
app.add_typer(server_app, name="server")

#: The help texts of options and arguments that several commands share.
JSON_HELP = "print one JSON object on stdout instead of text"
REGISTRY_HELP = "registry folder: every unit's passport versions"
UNIT_HELP = "the unit's serial number, e.g. AU-0001"

#: ``--json``, the flag of every command that can print its result as one JSON object: ``as_json: JsonFlag = False``
JsonFlag = Annotated[bool, typer.Option("--json", help=JSON_HELP)]


def _plain_type_words() -> None:
    """Help shows an option's value as a plain word (``PATH``, ``NUMBER``, ...) or its ``metavar``, and nothing for
    a flag or an argument (its name is shown), where typer's default shows Python type tags (``<bool>``,
    ``<list[Path]>``); arguments in the usage line as ``RUN`` and ``[V]``."""
    from typer import core

    words = {"float": "NUMBER", "int": "INTEGER", "str": "TEXT"}

    def display(self, ctx):
        if isinstance(self, core.TyperArgument) or getattr(self, "is_flag", False):
            return None
        if self.metavar is not None:
            return self.metavar
        desc = getattr(self, "type_descriptor", None)
        if desc is None:
            return None
        word = "PATH" if desc.is_path else words.get(self.bare_type().removeprefix("list[").removesuffix("]"), "VALUE")
        return word

    for cls in (getattr(core, "TyperArgument", None), getattr(core, "TyperOption", None)):
        if cls is not None and hasattr(cls, "display_type_rich"):
            cls.display_type_rich = display

    def usage_name(self) -> str:
        """``RUN`` (required), ``[V]`` (optional), ``RUN...`` in the usage line, where newer typer writes
        ``{RUN}``, which reads as a set of choices."""
        name = self.display_name_raw if self.required else f"[{self.display_name_raw}]"
        return name + ("..." if self.nargs != 1 else "")

    if hasattr(getattr(core, "TyperArgument", None), "_usage_display_name"):
        # the method is replaced on purpose (the usage name above)
        core.TyperArgument._usage_display_name = usage_name  # type: ignore[method-assign]


_plain_type_words()


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


def calibration_settings(thermal_model: str, constants_method: str, tol_normal_g: float, tol_range_g: float):
    """The settings of calibrate, fleet and serve from their options, each checked (a one-line error naming it)."""
    from pipeline.calibrate.settings import CalibrationSettings
    from pipeline.constants import CONSTANTS_METHODS
    from pipeline.thermal import THERMAL_MODELS
    from pipeline.verify import Tolerances

    if thermal_model not in THERMAL_MODELS:
        raise ThermocalError(
            f"unknown thermal model {thermal_model!r} ({', '.join(THERMAL_MODELS[1:])})", where="--thermal-model"
        )
    if constants_method not in CONSTANTS_METHODS:
        raise ThermocalError(
            f"unknown constants method {constants_method!r} ({', '.join(CONSTANTS_METHODS)})",
            where="--constants-method",
        )
    return CalibrationSettings(
        thermal_model=thermal_model,
        constants_method=constants_method,
        tolerances=Tolerances(normal_g=tol_normal_g, operating_range_g=tol_range_g),
    )
