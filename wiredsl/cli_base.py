"""What every `wiredsl` command shares, below cli.py and the commands in modules of their own (render, verify,
export): exit codes, `--diagnostics` and `report`, `guarded` (errors as diagnostics and exit 1, signals as a clean
exit, a bug as exit 3, never a traceback), and the checks of `-o` folder names and of a run's options.

Only click and the standard library at import (the lazy-import test and cold start).
"""

from __future__ import annotations

import contextlib
import os
import signal
import sys
import threading
from collections.abc import Callable
from functools import wraps

import click

EXIT_INVALID = 1
EXIT_INTERNAL = 3


def _colour() -> bool:
    return sys.stderr.isatty() and "NO_COLOR" not in os.environ


def report(diags, sources: dict[str, str], fmt: str) -> None:
    """Print diagnostics to stderr in text or JSON form."""
    from wiredsl.diagnostics import render, render_json

    if not diags:
        return
    if fmt == "json":
        sys.stderr.write(render_json(diags))
    else:
        sys.stderr.write(render(diags, sources, colour=_colour()))


class Stopped(BaseException):
    """SIGINT or SIGTERM arrived: unwind (every `finally` removes its temporaries), then exit 128 + signal."""

    def __init__(self, signum: int):
        super().__init__(signum)
        self.signum = signum


def _stop(signum: int, frame) -> None:
    from wiredsl import holding_stops, signal_stop

    for s in (signal.SIGINT, signal.SIGTERM):  # a second signal must not interrupt the clean-up
        signal.signal(s, signal.SIG_IGN)
    if holding_stops():  # an output folder's swap: it decides (files._swap)
        signal_stop(Stopped(signum))
        return
    raise signal_stop(Stopped(signum))  # kept: raised again at the next batch or write if compiled code drops it


def _stop_in(exc: BaseException | None) -> BaseException | None:
    """The Stopped or KeyboardInterrupt an exception was raised from or during, if any, or the signal's Stopped
    that the code it landed in dropped before this exception came."""
    from wiredsl import exception_chain, pending_stop

    found = next((e for e in exception_chain(exc) if isinstance(e, (Stopped, KeyboardInterrupt))), None)
    return found or pending_stop()


def _exit_stopped(exc: BaseException) -> None:
    signum = exc.signum if isinstance(exc, Stopped) else signal.SIGINT
    click.echo(f"wiredsl: stopped by {signal.Signals(signum).name}; temporary files removed", err=True)
    sys.exit(128 + signum)


def guarded(fn: Callable) -> Callable:
    """Turn WiredslError into diagnostics and exit 1, signals into a clean exit 130/143; never a traceback."""

    @wraps(fn)
    def wrapper(*args, **kwargs):
        from wiredsl import check_stop, clear_stops, pending_stop
        from wiredsl.diagnostics import WiredslError
        from wiredsl.files import OutputFolderError, UnwritableValue

        main_thread = threading.current_thread() is threading.main_thread()
        if main_thread:
            clear_stops()  # (a signal an earlier command in this process took is not this one's)
        previous = {s: signal.signal(s, _stop) for s in (signal.SIGINT, signal.SIGTERM)} if main_thread else {}
        try:
            try:
                out = fn(*args, **kwargs)
                if main_thread:
                    check_stop()  # a signal dropped where it landed still stops the run: never exit 0 after one
                if not sys.stdout.closed:  # (the language server's client closes it on exit)
                    sys.stdout.flush()  # here, where a closed pipe is caught, not at exit
                return out
            except BrokenPipeError:
                if not _stdout_closed():
                    raise  # another pipe (a worker's): not the reader of our output going away
                _quiet_exit()
            except WiredslError as err:
                stop = pending_stop()
                if stop is not None:  # a plug-in caught the signal's exception and failed instead
                    _exit_stopped(stop)
                if os.environ.get("WIREDSL_DEBUG") and getattr(err, "detail", None):  # a plug-in's own traceback
                    click.echo(err.detail.rstrip("\n"), err=True)
                report(err.diagnostics, _sources(err.diagnostics), kwargs.get("diagnostics", "text"))
                sys.exit(EXIT_INVALID)
            except (Stopped, KeyboardInterrupt) as exc:
                _exit_stopped(exc)
            except (click.exceptions.Exit, click.ClickException, SystemExit):
                raise
            except OutputFolderError as exc:
                raise click.BadParameter(str(exc), param_hint="-o") from None
            except UnwritableValue as exc:  # the input drove a number out of range; nothing was written
                click.echo(f"wiredsl: error: nothing written: {exc}", err=True)
                sys.exit(EXIT_INVALID)
            except OSError as exc:  # the disk, not the input or a bug: say which file and why
                where = f" {exc.filename}" if getattr(exc, "filename", None) else ""
                click.echo(f"wiredsl: error: cannot write{where}: {exc.strerror or exc}", err=True)
                sys.exit(EXIT_INVALID)
            except Exception as exc:  # a bug: say so plainly, keep the traceback for WIREDSL_DEBUG
                stop = _stop_in(exc)
                if stop is not None:  # the signal landed inside compiled code, which wraps it in a SystemError
                    _exit_stopped(stop)
                if os.environ.get("WIREDSL_DEBUG"):
                    raise
                click.echo(f"wiredsl: internal error ({type(exc).__name__}: {exc}); this is a bug, please report it "
                           "with the input (set WIREDSL_DEBUG=1 for a traceback)", err=True)
                sys.exit(EXIT_INTERNAL)
        except (Stopped, KeyboardInterrupt) as exc:  # the signal came while an error was being reported
            _exit_stopped(exc)
        finally:
            for sig, handler in previous.items():
                signal.signal(sig, handler)
            if main_thread:
                clear_stops()

    return wrapper


def _stdout_closed() -> bool:
    """Has the reader of stdout gone away (`wiredsl build -o - | head`)? Not an error: we stop quietly."""
    import select

    try:
        poll = select.poll()
        poll.register(sys.stdout.fileno(), select.POLLOUT)
        return any(ev & (select.POLLERR | select.POLLHUP) for _, ev in poll.poll(0))
    except (AttributeError, OSError, ValueError):  # no real file descriptor (tests), or no poll
        return False


def _quiet_exit() -> None:
    """Exit 0 after the reader closed stdout; what Python still holds for it goes to /dev/null, so the
    interpreter's last flush does not complain either."""
    devnull = os.open(os.devnull, os.O_WRONLY)
    os.dup2(devnull, sys.stdout.fileno())
    sys.exit(0)


def _sources(diags) -> dict[str, str]:
    from wiredsl.diagnostics import read_sources

    return read_sources(diags)


class FiniteRange(click.FloatRange):
    """click.FloatRange that refuses NaN (which every comparison lets through) and the infinities."""

    name = "finite float range"

    def convert(self, value, param, ctx):
        import math

        number = click.FLOAT.convert(value, param, ctx)
        if not math.isfinite(number):
            self.fail(f"{value!r} is not a finite number", param, ctx)
        return super().convert(number, param, ctx)


diagnostics_option = click.option("--diagnostics", type=click.Choice(["text", "json"]), default="text",
                                  show_default=True, help="Form of diagnostics on stderr.")


def folder_name(out, suffixes: tuple[str, ...], inside: str):
    """-o of a command that writes a folder: a name that looks like one of its files is a mistake."""
    if out.exists() and not out.is_dir():
        raise click.BadParameter(f"must name a folder: {out} is a file", param_hint="-o")
    if out.suffix.lower() in suffixes and not out.is_dir():
        raise click.BadParameter(f"{out} looks like a file name; -o names the output folder ({inside})",
                                 param_hint="-o")
    return out


@contextlib.contextmanager
def setup_errors():
    """A run's options that do not fit the scene: a usage error naming the option."""
    from wiredsl.run import RunSetupError

    try:
        yield
    except RunSetupError as err:
        raise click.BadParameter(str(err), param_hint=err.option) from None


def auto_visibility(scene, world, program, poses, cameras: str, repeats: int, fmt: str) -> str:
    """`--visibility auto` of build and export: exact or scene (run.choose_visibility) for `poses` (None: every
    one) with `cameras` ("both" or "left"), `repeats` times; W129 (at run.w129_span) when the scene's faces
    would hide something that this build keeps."""
    from wiredsl import run as runs
    from wiredsl.diagnostics import Diagnostic

    n_poses = len(poses) if poses else len(scene.path.poses) if scene.path is not None else 0
    choice = runs.choose_visibility(scene, world, n_poses * (2 if cameras == "both" else 1) * repeats)
    if choice.warning is not None:
        report([Diagnostic("warning", "W129", choice.warning, runs.w129_span(program, scene))], program.sources, fmt)
    return choice.mode
