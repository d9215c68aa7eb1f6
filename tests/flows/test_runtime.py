"""flows.runtime.exit_guarded: what a command's exit status and stderr are when Ctrl-C lands in a bad place."""

from __future__ import annotations

import subprocess
import sys
import textwrap
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]

_COMMAND = """
import signal, sys, time
from flows.runtime import exit_guarded

class Finalised:
    def __del__(self):
        {in_finaliser}
        for _ in range(1000):
            pass

def body():
    Finalised()
    end = time.monotonic() + {seconds}
    while time.monotonic() < end:  # the rest of the command
        time.sleep(0.01)
    print("finished")
    return 0

exit_guarded(body)
"""


def _run(in_finaliser: str, seconds: float) -> subprocess.CompletedProcess:
    script = textwrap.dedent(_COMMAND).replace("{in_finaliser}", in_finaliser).replace("{seconds}", str(seconds))
    return subprocess.run(
        [sys.executable, "-c", script], cwd=ROOT, capture_output=True, text=True, timeout=60, check=False
    )


def test_ctrl_c_inside_a_finaliser_still_stops_the_command():
    """SIGINT while Python runs a finaliser (here a __del__; in the job process of the local server it was a weakref
    callback, and `thermocal calibrate` went on and ended 0): the command stops well before its 10 s, exit 130,
    one line on stderr, nothing of the command's own output."""
    done = _run("signal.raise_signal(signal.SIGINT)", seconds=10.0)
    assert done.returncode == 130, done.stderr
    assert done.stderr.splitlines() == ["thermocal: aborted"]
    assert done.stdout == ""


def test_other_exceptions_in_finalisers_are_reported_as_before():
    """Any other exception a finaliser raises goes to Python's own hook ("Exception ignored in ..."), the command
    goes on and ends 0."""
    done = _run("raise ValueError('in a finaliser')", seconds=0.2)
    assert done.returncode == 0, done.stderr
    assert done.stdout == "finished\n"
    assert "Exception ignored in" in done.stderr and "ValueError: in a finaliser" in done.stderr


_WRAPPED = """
import signal
from flows.runtime import exit_guarded

class SerializationError(Exception):
    pass

def serialize():  # a library that turns whatever its callback raises into an error of its own (pydantic-core)
    try:
        signal.raise_signal(signal.SIGINT)
    except BaseException as e:
        raise SerializationError(f"Error calling function `_ser_model`: {type(e).__name__}:") from None

def body():
    serialize()
    print("finished")
    return 0

exit_guarded(body)
"""


def test_ctrl_c_turned_into_a_library_error_is_still_ctrl_c():
    """SIGINT while Prefect's pydantic serializer ran: pydantic-core turns the KeyboardInterrupt into its own
    PydanticSerializationError, and `thermocal calibrate` said `internal error: PydanticSerializationError: Error
    calling function `_ser_model`: KeyboardInterrupt:` and exited 3 (a CI run of test_localserver's Ctrl-C test).
    Any exception after the user's Ctrl-C is the Ctrl-C: exit 130, one line."""
    done = subprocess.run(
        [sys.executable, "-c", textwrap.dedent(_WRAPPED)], cwd=ROOT, capture_output=True, text=True, timeout=60
    )
    assert done.returncode == 130, done.stderr
    assert done.stderr.splitlines() == ["thermocal: aborted"]
    assert done.stdout == ""


def test_a_library_error_without_ctrl_c_is_an_internal_error():
    """The same error without a Ctrl-C before it stays an internal error (exit 3, one line)."""
    script = textwrap.dedent(_WRAPPED).replace("signal.raise_signal(signal.SIGINT)", "raise ValueError('no')")
    done = subprocess.run([sys.executable, "-c", script], cwd=ROOT, capture_output=True, text=True, timeout=60)
    assert done.returncode == 3, done.stderr
    assert done.stderr.splitlines() == [
        "thermocal: internal error: SerializationError: Error calling function `_ser_model`: ValueError:"
    ]
