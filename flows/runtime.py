"""Prefect defaults of thermocal: where flow runs are recorded, no telemetry, no heartbeat thread; progress lines.

Call :func:`prefect_defaults` before importing prefect. Flow runs are recorded on ``PREFECT_API_URL`` when it is
set (a server of the user's), else on thermocal's local server (:mod:`flows.localserver`, started on first use);
a program that calls :func:`flows.calibrate.run_calibrate` or :func:`flows.fleet.run_fleet` with
``local_server=False`` leaves the choice to Prefect (without ``PREFECT_API_URL``: its per-process ephemeral mode).
"""

from __future__ import annotations

import contextlib
import os
import sys
import time
from typing import Any

_DEFAULTS = {
    "PREFECT_SERVER_ANALYTICS_ENABLED": "false",
    "DO_NOT_TRACK": "1",
    # Prefect's ephemeral server (``local_server=False``) starts in ~8-13 s here; give slow machines room
    "PREFECT_SERVER_EPHEMERAL_STARTUP_TIMEOUT_SECONDS": "120",
    "PREFECT_LOGGING_LEVEL": "WARNING",
}


def prefect_defaults() -> None:
    import logging

    for k, v in _DEFAULTS.items():
        os.environ.setdefault(k, v)
    # "EventsWorker - Still processing items" at exit is Prefect draining its event queue, not a problem of ours
    logging.getLogger("EventsWorker").setLevel(logging.ERROR)


@contextlib.contextmanager
def flow_settings(local_server: bool = True):
    """Settings in force while a flow runs: the API it is recorded on (``PREFECT_API_URL``, else thermocal's local
    server; with ``local_server=False`` Prefect's own choice, see the module doc), no heartbeat thread (it costs
    ~1 s per flow run)."""
    prefect_defaults()
    from prefect.settings import PREFECT_API_URL, PREFECT_FLOWS_HEARTBEAT_FREQUENCY, temporary_settings

    updates: dict[Any, Any] = {}
    if PREFECT_FLOWS_HEARTBEAT_FREQUENCY.value() is not None:
        updates[PREFECT_FLOWS_HEARTBEAT_FREQUENCY] = None
    if local_server and not PREFECT_API_URL.value():
        from .localserver import ensure_server

        updates[PREFECT_API_URL] = ensure_server()["api_url"]
    with temporary_settings(updates):
        yield


@contextlib.contextmanager
def quiet_task_failures():
    """A failed task or flow run makes Prefect log the exception with its traceback; the command line reports a
    ThermocalError in one line itself, so Prefect's run loggers are held at CRITICAL meanwhile (the flow's
    warnings are part of the command's own output)."""
    import logging

    loggers = [logging.getLogger(n) for n in ("prefect.task_runs", "prefect.flow_runs")]
    levels = [lg.level for lg in loggers]
    for lg in loggers:
        lg.setLevel(logging.CRITICAL)
    try:
        yield
    finally:
        for lg, lvl in zip(loggers, levels):
            lg.setLevel(lvl)


@contextlib.contextmanager
def run_logs_off_console(off: bool = True):
    """While ``off``: the flow and task runs' log lines go to the Prefect API only (the run's logs in the UI), not
    to the console handler on stderr, so that a command whose stderr is not a terminal writes nothing there but
    its own result line. Call after importing prefect (its logging is set up then)."""
    import logging

    loggers = [logging.getLogger(n) for n in ("prefect.task_runs", "prefect.flow_runs")] if off else []
    before = [lg.propagate for lg in loggers]
    for lg in loggers:
        lg.propagate = False
    try:
        yield
    finally:
        for lg, p in zip(loggers, before):
            lg.propagate = p


def pool_worker_init() -> None:
    """Initializer of a process pool of thermocal's (the fleet's): leave at once when the process that made the
    pool is gone (killed: no orphan keeps computing), then warm up (:func:`pipeline.calibrate.fleet.prepare_worker`).
    This module imports little, so a worker watches its parent within its first second."""
    import multiprocessing
    import threading
    from multiprocessing.connection import wait

    parent = multiprocessing.parent_process()

    def leave_with_parent():
        wait([parent.sentinel])
        os._exit(1)

    if parent is not None:
        threading.Thread(target=leave_with_parent, daemon=True, name="thermocal-parent-watch").start()
    from pipeline.calibrate.fleet import prepare_worker

    prepare_worker()


class Steps:
    """Progress of a long command on stderr, one line per step (``thermocal: calibrate: fit (1.2 s)``), only when
    stderr is a terminal: nothing is added to a piped or ``--json`` command's output."""

    def __init__(self, command: str, stream=None):
        self.command = command
        self.stream = stream
        self.t0 = time.perf_counter()
        out = self.stream or sys.stderr
        try:
            self.on = bool(out.isatty())
        except (AttributeError, ValueError):
            self.on = False

    def __call__(self, step: str) -> None:
        if self.on:
            out = self.stream or sys.stderr
            out.write(f"thermocal: {self.command}: {step} ({time.perf_counter() - self.t0:.1f} s)\n")
            out.flush()


class ClosedPipeQuiet:
    """``sys.stdout`` while a command runs: when the reader of a pipe goes away (``thermocal ... | head -3``), the
    rest of the output is dropped without a word and the command carries on to its end (registry writes included,
    exit status unchanged); the file descriptor is pointed at the null device so that the interpreter's last flush
    finds nothing to complain about. Control characters written are escaped (:func:`pipeline.words.printable`):
    what a command prints is text, never terminal commands."""

    def __init__(self, stream):
        self._stream = stream
        self.reader_gone = False

    def write(self, s: str) -> int:
        if not self.reader_gone:
            try:
                from pipeline.words import printable

                return self._stream.write(printable(s))
            except BrokenPipeError:
                self._drop()
        return len(s)

    def flush(self) -> None:
        if not self.reader_gone:
            try:
                self._stream.flush()
            except BrokenPipeError:
                self._drop()

    def _drop(self) -> None:
        self.reader_gone = True
        try:
            fd = self._stream.fileno()
        except (AttributeError, OSError, ValueError):  # not a file (a test's capture)
            return
        null = os.open(os.devnull, os.O_WRONLY)
        try:
            os.dup2(null, fd)
        finally:
            os.close(null)

    def __getattr__(self, name):
        return getattr(self._stream, name)


def exit_guarded(body) -> None:
    """Run ``body()`` (a command; returns its exit status) as the console script does and exit with its status:
    ``sys.stdout`` is :class:`ClosedPipeQuiet` meanwhile; a :class:`pipeline.errors.ThermocalError` is one line on
    stderr and exit 2, Ctrl-C ``thermocal: aborted`` and 130, any other exception one line (``internal error``,
    the traceback with THERMOCAL_DEBUG=1) and 3. The one guard of :func:`flows.cli.main` and
    :func:`flows.console.main`. Control characters in what is printed are escaped (:func:`pipeline.words.printable`:
    a serial or a name holding ANSI escapes is shown, not obeyed); Python's warnings (numpy's floating-point
    RuntimeWarnings, libraries' deprecations) are not printed (with THERMOCAL_DEBUG=1 they are): a command says what
    matters in its own lines."""
    import warnings

    from pipeline.errors import ThermocalError
    from pipeline.words import printable

    stdout = sys.stdout
    sys.stdout = ClosedPipeQuiet(stdout)
    quiet = warnings.catch_warnings()
    quiet.__enter__()
    if not os.environ.get("THERMOCAL_DEBUG"):
        warnings.simplefilter("ignore")
    lost = _LostInterrupts(sys.unraisablehook)
    sys.unraisablehook = lost
    interrupted = _Interrupted.install()
    try:
        code = body()
        if lost.count:  # the interrupt was swallowed and its repeat came too late: still the user's Ctrl-C
            raise KeyboardInterrupt
    except ThermocalError as e:
        print(f"thermocal: error: {printable(e.one_line(), lines=False)}", file=sys.stderr)
        code = 2
    except KeyboardInterrupt:
        print("thermocal: aborted", file=sys.stderr)
        code = 130
    except SystemExit:
        raise
    except Exception as e:
        if interrupted is not None and interrupted.seen:  # the user's Ctrl-C, wrapped by a library on its way up
            print("thermocal: aborted", file=sys.stderr)
            code = 130
        elif os.environ.get("THERMOCAL_DEBUG"):
            raise
        else:
            text = printable(" ".join(str(e).split()), lines=False)
            print(f"thermocal: internal error: {type(e).__name__}: {text}", file=sys.stderr)
            code = 3
    finally:
        if interrupted is not None:
            interrupted.restore()
        sys.unraisablehook = lost.hook
        sys.stdout = stdout
        quiet.__exit__(None, None, None)
    sys.exit(code)


#: seconds after a Ctrl-C swallowed by a finaliser that it is raised again (:class:`_LostInterrupts`)
_INTERRUPT_AGAIN_S = 0.05


class _Interrupted:
    """SIGINT's handler while a command runs: notes that the user pressed Ctrl-C, then does what the handler before
    it did (Python's: raise ``KeyboardInterrupt``). A library may turn that KeyboardInterrupt into an error of its
    own on its way up (pydantic's serializer, called by Prefect, raises ``PydanticSerializationError: Error calling
    function ...: KeyboardInterrupt``): :func:`exit_guarded` still answers it as Ctrl-C (``thermocal: aborted``,
    130), not as an internal error."""

    def __init__(self, previous) -> None:
        self.previous = previous
        self.seen = False

    @classmethod
    def install(cls) -> _Interrupted | None:
        """The handler, installed where a handler can be (the main thread) and the one before it is Python's or
        another callable (an ignored SIGINT stays ignored); else None."""
        import signal
        import threading

        if threading.current_thread() is not threading.main_thread():
            return None
        previous = signal.getsignal(signal.SIGINT)
        if not callable(previous):
            return None
        handler = cls(previous)
        signal.signal(signal.SIGINT, handler)
        return handler

    def __call__(self, signum, frame) -> None:
        self.seen = True
        self.previous(signum, frame)

    def restore(self) -> None:
        import signal

        signal.signal(signal.SIGINT, self.previous)


class _LostInterrupts:
    """``sys.unraisablehook`` while a command runs: Ctrl-C (``KeyboardInterrupt``) that lands while Python runs a
    finaliser (a ``__del__``, a weakref callback, a generator closed by the garbage collector) cannot propagate,
    and Python would print "Exception ignored in ..." and go on as if nothing happened: the command would end 0
    with a traceback on stderr. Here it is counted and the signal raised again, so the interrupt reaches the
    command's own code (:func:`exit_guarded`: ``thermocal: aborted``, 130). Any other unraisable exception goes to
    the previous hook (``hook``) as before."""

    def __init__(self, hook) -> None:
        self.hook = hook
        self.count = 0

    def __call__(self, unraisable) -> None:
        import signal
        import threading

        if not isinstance(unraisable.exc_value, KeyboardInterrupt):
            self.hook(unraisable)
            return
        self.count += 1
        # sent again a moment later from another thread, once this finaliser is over (raised from here, its
        # handler would run at once, inside the finaliser again); lost again, it comes back again
        main = threading.main_thread().ident
        again = threading.Timer(_INTERRUPT_AGAIN_S, signal.pthread_kill, (main, signal.SIGINT))
        again.daemon = True
        with contextlib.suppress(RuntimeError):  # no new thread while the interpreter shuts down
            again.start()
