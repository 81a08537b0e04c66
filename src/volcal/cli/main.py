"""The ``volcal`` command line.

Each subcommand lives next to the code it drives and registers itself through an
``add_parser(subparsers)`` function listed in ``_COMMANDS``; the handler it sets as
``func`` returns a process exit code.  Exit codes: 0 success, 1 a computation that ran
but failed (solver did not converge, ...), 2 bad usage or bad input.
"""

from __future__ import annotations

import argparse
import importlib
import logging
import sys

from volcal.base.exceptions import InputError, SolverError

# module path of each command's ``add_parser``; kept as strings so that ``volcal --help``
# does not import CasADi or SymPy.
_COMMANDS = [
    "volcal.cli.commands.models",
    "volcal.iso230_2.cli",
    "volcal.cli.commands.simulate",
    "volcal.cli.commands.demo",
    "volcal.cli.commands.identify",
    "volcal.cli.commands.compare",
    "volcal.cli.commands.predict",
    "volcal.cli.commands.codegen",
    "volcal.cli.commands.analyze",
    "volcal.cli.commands.plan",
    "volcal.cli.commands.mc",
    "volcal.cli.commands.compensate",
    "volcal.cli.commands.report",
]


class UserError(Exception):
    """An error caused by the user's input: printed without a traceback, exit code 2."""


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="volcal",
        description="Identify machine-tool geometric errors from multilateration length data.",
    )
    parser.add_argument("-q", "--quiet", action="store_true", help="print only errors")
    parser.add_argument(
        "-v", "--verbose", action="count", default=0, help="more output (repeat for debug output)"
    )
    from volcal import __version__

    parser.add_argument("--version", action="version", version=f"volcal {__version__}")
    parser.add_argument(
        "--project",
        metavar="FILE",
        help="project file with one table of settings per command (default ./volcal.toml "
        "when present); flags override it",
    )
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    for modname in _COMMANDS:
        importlib.import_module(modname).add_parser(sub)
    # -q / -v also after the command name (`volcal identify ... -q`); SUPPRESS keeps a
    # value given before the command when the command line does not repeat it
    for cmd in sub.choices.values():
        cmd.add_argument(
            "-q",
            "--quiet",
            action="store_true",
            default=argparse.SUPPRESS,
            help="print only errors",
        )
        cmd.add_argument(
            "-v",
            "--verbose",
            action="count",
            default=argparse.SUPPRESS,
            help="more output (repeat for debug output)",
        )
        if "--force" not in cmd._option_string_actions:
            cmd.add_argument(
                "--force",
                action="store_true",
                default=False,
                help="replace an earlier output of this command in the output "
                "folder (never an input or a folder volcal did not write)",
            )
    return parser


_SIGNALLED = False


def _terminate(signum, frame):  # pragma: no cover - exercised through a subprocess
    # SIGTERM takes the same path as Ctrl-C: finally blocks remove temporary folders and
    # stop worker processes
    global _SIGNALLED
    _SIGNALLED = True
    from volcal.base.folders import interrupt_deferred
    from volcal.base.interrupts import note_signal

    note_signal(signum)  # a solver that catches the KeyboardInterrupt still stops the command

    if interrupt_deferred(signum):  # a file is being renamed into place: raise right after
        return
    raise KeyboardInterrupt(f"signal {signum}")


def _exit_soon(code: int, seconds: float = 10.0) -> None:  # pragma: no cover - subprocess
    """After a signal, the process must end even if a library's exit handler waits on a
    worker that was stopped mid-task: a daemon thread ends it after ``seconds``."""
    import os
    import threading
    import time

    def later() -> None:
        time.sleep(seconds)
        sys.stderr.flush()
        os._exit(code)

    threading.Thread(target=later, daemon=True).start()


def _exit_now(code: int) -> None:  # pragma: no cover - ends the process
    """End the program without the interpreter's teardown (0.1-0.2 s of freeing modules
    and objects), for a command that has closed everything it opened and asks for it
    (``args.exit_now``; ``args.exit_now_on_error`` for the exit on a bad input, code 2),
    and after an interruption by a signal (code 130);
    only when running as the program (``main()`` without argv),
    never for a caller of :func:`main`, nor under a profiler or a tracer."""
    import os

    logging.shutdown()
    for stream in (sys.stdout, sys.stderr):
        try:
            stream.flush()
        except Exception:
            pass
    os._exit(code)


class _Formatter(logging.Formatter):
    """Log lines as the command's other messages: ``volcal identify: warning: ...``."""

    def __init__(self, command: str) -> None:
        super().__init__()
        self.command = command

    def format(self, record: logging.LogRecord) -> str:
        return f"volcal {self.command}: {record.levelname.lower()}: {record.getMessage()}"


def _warning_printer(command: str, quiet: bool):
    """A ``warnings.showwarning`` that prints ``volcal <command>: warning: <message>``:
    the user is told what is wrong with the input, not which line of volcal's source
    noticed it (Python's default prints the source path, line number and code line).
    Warnings of other packages keep their category name; ``-q`` silences them all."""

    def show(message, category, filename, lineno, file=None, line=None) -> None:
        if quiet:
            return
        ours = category.__module__.split(".")[0] in ("volcal", "builtins") and issubclass(
            category, UserWarning
        )
        tail = "" if ours else f" ({category.__name__})"
        stream = file if file is not None else sys.stderr
        try:
            print(f"volcal {command}: warning: {message}{tail}", file=stream)
        except (OSError, ValueError):  # a closed stream: nothing to tell
            pass

    return show


PROJECT_FILE = "volcal.toml"


def _project_value(path, command: str, key: str, value, action: argparse.Action):
    """A project-file value checked and converted as the command line would convert the
    option's text: a flag takes true / false, a number option a TOML number (or a string
    that reads as one), a repeatable option an array; a value the option refuses is an
    InputError naming the file, the table and the key (not the flag, which the user did
    not type)."""
    where = f"[{command}] {key}"

    def what(v) -> str:
        kinds = {bool: "boolean", int: "integer", float: "number", str: "string"}
        kind = kinds.get(type(v), "array" if isinstance(v, list) else "table")
        return f"{kind} {v!r}"

    def bad(expected: str, v=value):
        return InputError(f"{where}: expected {expected}, got {what(v)}", source=str(path))

    if action.nargs == 0:  # --flag (store_true / store_false)
        if not isinstance(value, bool):
            raise bad("true or false")
        return value
    if isinstance(action, argparse._AppendAction):  # noqa: SLF001
        items = value if isinstance(value, list) else [value]
        return [_project_item(where, path, action, v, bad) for v in items]
    return _project_item(where, path, action, value, bad)


def _project_item(where: str, path, action: argparse.Action, v, bad):
    """One value of an option (see :func:`_project_value`)."""
    from pathlib import Path

    t = action.type
    if t is int:
        if isinstance(v, bool) or not isinstance(v, (int, str)):
            raise bad("an integer", v)
    elif t is float:
        if isinstance(v, bool) or not isinstance(v, (int, float, str)):
            raise bad("a number", v)
    elif isinstance(v, (bool, list, dict)) or not isinstance(v, (str, int, float)):
        raise bad("a path" if t is Path else "a single value (a string or a number)", v)
    if t is None and action.choices is None and not isinstance(v, str):
        v = str(v)  # a name given as a number (`--model 3` would be the text "3")
    if callable(t):
        try:
            v = t(v)
        except (TypeError, ValueError, argparse.ArgumentTypeError, InputError) as exc:
            if t is int:
                raise bad("an integer", v) from None
            if t is float:
                raise bad("a number", v) from None
            if t is Path:
                raise bad("a path", v) from None
            raise InputError(f"{where}: {exc}", source=str(path)) from None
        if t is float and not isinstance(v, float):
            v = float(v)
    if action.choices is not None and v not in action.choices:
        raise InputError(
            f"{where}: expected one of {', '.join(map(str, action.choices))}, got {v!r}",
            source=str(path),
        )
    return v


def _project_defaults(parser: argparse.ArgumentParser, argv: list[str]) -> str | None:
    """Apply a project file's settings as defaults of the command about to run, so that a
    run needs no long flag list and flags still override it.

    The file is ``--project FILE`` or ``./volcal.toml``; one table per command, keys are
    the command's long options without dashes (``[identify] model = "mcv754_wxyzt"``,
    ``strategy = "joint"``, ``out = "result"``).  Parsed with tomllib: data, never code.
    Returns the file used (None: none).  Unknown commands or keys are an InputError
    naming the file, table and key."""
    import tomllib
    from pathlib import Path

    path = None
    if "--project" in argv:
        i = argv.index("--project")
        if i + 1 >= len(argv):
            raise InputError("--project needs a file name")
        path = Path(argv[i + 1])
        del argv[i : i + 2]
        if not path.is_file():
            raise InputError("no such project file", source=str(path))
    elif Path(PROJECT_FILE).is_file():
        path = Path(PROJECT_FILE)
    if path is None:
        return None
    try:
        doc = tomllib.loads(path.read_text(encoding="utf-8"))
    except (tomllib.TOMLDecodeError, UnicodeDecodeError) as exc:
        raise InputError(f"not valid TOML: {exc}", source=str(path)) from None
    sub = next(
        a
        for a in parser._actions
        if isinstance(a, argparse._SubParsersAction)  # noqa: SLF001
    )
    unknown = sorted(set(doc) - set(sub.choices))
    if unknown:
        raise InputError(
            f"unknown command table(s) [{'], ['.join(unknown)}]; commands: "
            f"{', '.join(sub.choices)}",
            source=str(path),
        )
    not_tables = sorted(k for k, v in doc.items() if not isinstance(v, dict))
    if not_tables:
        raise InputError(
            f"'{not_tables[0]}' must be a table of settings ([{not_tables[0]}] with one "
            "key per option), got a single value",
            source=str(path),
        )
    command = next((a for a in argv if a in sub.choices), None)
    if command is None or command not in doc:
        return str(path)
    cmd = sub.choices[command]
    dests = {
        a.dest: a
        for a in cmd._actions  # noqa: SLF001
        if a.option_strings and a.dest not in ("help", "quiet", "verbose")
    }
    values = {}
    for key, value in doc[command].items():
        dest = key.replace("-", "_")
        if dest not in dests:
            raise InputError(
                f"[{command}] has no option '{key}'; options: "
                f"{', '.join(sorted(k.replace('_', '-') for k in dests))}",
                source=str(path),
            )
        action = dests[dest]
        value = _project_value(path, command, key, value, action)
        # a relative path is relative to the project file
        if isinstance(value, Path) and not value.is_absolute():
            value = path.parent / value
        values[dest] = value
        action.required = False  # given by the file; a flag still overrides it
    for group in cmd._mutually_exclusive_groups:  # noqa: SLF001
        if any(a.dest in values for a in group._group_actions):  # noqa: SLF001
            group.required = False
    cmd.set_defaults(**values)
    return str(path)


def _what_stays(args: argparse.Namespace) -> str:
    """:func:`_describe_what_stays`, never raising: it runs inside the handlers of an
    error or an interrupt, where a folder that cannot be listed must not end in a
    traceback."""
    try:
        return _describe_what_stays(args)
    except OSError:
        return "what stays of the output could not be listed"


def _describe_what_stays(args: argparse.Namespace) -> str:
    """What an interrupted or failed command leaves behind, as one true clause: nothing,
    the earlier output (untouched: outputs are renamed into place whole), or the resumable
    pieces (``volcal mc``'s finished chunks, ``volcal plan``'s checkpoints) and how to
    resume them."""
    from pathlib import Path

    said = []
    ckpt = getattr(args, "checkpoint", None)
    if ckpt is not None and Path(ckpt).is_dir() and any(Path(ckpt).iterdir()):
        said.append(
            f"the search checkpoints in {ckpt} stay: rerun with --checkpoint {ckpt} to resume"
        )
    out = getattr(args, "out", None)
    if out is None or str(out) == "-":
        return "; ".join(said) or "nothing was written"
    out = Path(out)
    samples = out / "samples"
    if args.command == "mc" and samples.is_dir() and not (out / "manifest.json").is_file():
        chunks = list(samples.rglob("chunk*.npz"))
        size = sum(f.stat().st_size for f in chunks)
        said.append(
            f"{samples} keeps the {len(chunks)} finished chunk(s) of trials "
            f"({size / 1e6:.1f} MB): rerun the same command to resume from them "
            "(or delete the folder to start afresh); no result file was written"
        )
    elif getattr(args, "out_existed", False) and out.exists():
        said.append(f"{out} keeps what it held before, untouched")
    elif out.exists():
        said.append(f"{out} holds no result")
    else:
        said.append(f"nothing was written to {out}")
    return "; ".join(said)


def _os_error(exc: OSError, args: argparse.Namespace) -> str:
    """The message for an operating-system error: the system's words, the path, and for
    a full disk or quota the output and the device it is on, then what stays."""
    import errno

    out = getattr(args, "out", None)
    target = out if out is not None and str(out) != "-" else getattr(exc, "filename", None)
    what = exc.strerror or str(exc)
    if exc.errno in (errno.ENOSPC, errno.EDQUOT, errno.EFBIG) and target is not None:
        from volcal.base.folders import describe_device

        return (
            f"{what} while writing {target} (on {describe_device(target)}); "
            f"{_what_stays(args)}; free some space there"
            + (" or choose another --out" if target is out else "")
        )
    where = f" ({exc.filename})" if getattr(exc, "filename", None) else ""
    return f"{what}{where}; {_what_stays(args)}"


def main(argv: list[str] | None = None) -> int:
    """The ``volcal`` program: run the command of ``argv`` (default: ``sys.argv[1:]``, as
    the program) and return its exit code."""
    from volcal.base.processes import pause_gc, resume_gc

    # as the program, the start-up imports run without the cyclic garbage collector (never
    # in a caller's process): a command resumes it once its own imports are done, the
    # others before they run (volcal.base.processes.pause_gc)
    gc_paused = argv is None and sys.getprofile() is None and sys.gettrace() is None and pause_gc()
    try:
        return _main(argv, gc_paused)
    finally:
        resume_gc()  # whatever ended the command (a no-op once resumed)


def _main(argv: list[str] | None, gc_paused: bool) -> int:
    from volcal.base.processes import resume_gc

    as_program = argv is None
    # a profiler or coverage writes its data at exit: never skip the teardown under one
    untraced = as_program and sys.getprofile() is None and sys.gettrace() is None
    parser = build_parser()
    argv = list(sys.argv[1:] if argv is None else argv)
    try:
        project = _project_defaults(parser, argv)
    except InputError as exc:
        print(f"volcal: error: {exc}", file=sys.stderr)
        return 2
    args = parser.parse_args(argv)
    args.project_file = project
    level = (
        logging.ERROR
        if args.quiet
        else (
            logging.DEBUG if args.verbose > 1 else logging.INFO if args.verbose else logging.WARNING
        )
    )
    logging.basicConfig(level=level)
    if not args.quiet:  # stages longer than a moment report on stderr (volcal.base.progress)
        from volcal.base import progress

        progress.enable()
    if not getattr(args, "func", None):
        parser.print_help()
        return 2
    # small dense problems: one BLAS thread is much faster than a contended pool
    from volcal.base.threads import set_blas_threads

    set_blas_threads(1)
    import os
    import signal
    import threading

    from volcal.base.folders import output_policy

    if threading.current_thread() is threading.main_thread():
        from volcal.base.interrupts import clear

        clear()  # a signal noted by an earlier command of this process is not this one's
        previous = signal.signal(signal.SIGTERM, _terminate)
        prev_int = signal.getsignal(signal.SIGINT)
        if prev_int is signal.default_int_handler:
            signal.signal(signal.SIGINT, _terminate)
    else:  # pragma: no cover
        previous = prev_int = None
    out = getattr(args, "out", None)
    args.out_existed = out is not None and os.path.lexists(str(out))
    # warnings and log lines as the command's other messages: `volcal identify: warning: ...`
    import warnings

    formatters = []
    for handler in logging.getLogger().handlers:
        if type(handler) is logging.StreamHandler:  # basicConfig's, not a test's capture
            formatters.append((handler, handler.formatter))
            handler.setFormatter(_Formatter(args.command))
    previous_show = warnings.showwarning
    warnings.showwarning = _warning_printer(args.command, bool(args.quiet))
    args.gc_paused = gc_paused and getattr(args, "imports_gc_paused", False)
    if gc_paused and not args.gc_paused:
        resume_gc()
    interrupted = False
    try:
        with output_policy(bool(getattr(args, "force", False))):
            code = int(args.func(args) or 0)
        if untraced and getattr(args, "exit_now", False):
            _exit_now(code)
        return code
    except (UserError, InputError, FileNotFoundError) as exc:
        # Validation errors carry file/row/column in their message: no traceback.
        print(f"volcal {args.command}: error: {exc}", file=sys.stderr)
        if untraced and getattr(args, "exit_now_on_error", False):
            # the command closed what it opened: a bad table is reported without the
            # 0.1 s of freeing pandas' and numpy's modules
            _exit_now(2)
        return 2
    except SolverError as exc:
        print(f"volcal {args.command}: solver failed: {exc}", file=sys.stderr)
        return 1
    except BrokenPipeError:
        # output piped into e.g. `head`, which closed early: not an error of ours
        sys.stderr.close()
        return 0
    except OSError as exc:
        # read-only folder, a file where a folder is expected, a full disk, ...
        print(f"volcal {args.command}: error: {_os_error(exc, args)}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print(f"volcal {args.command}: interrupted; {_what_stays(args)}", file=sys.stderr)
        if _SIGNALLED:
            if untraced:
                interrupted = True  # ended below, once this clause has freed its frames
            else:
                _exit_soon(130)
        return 130
    finally:
        warnings.showwarning = previous_show
        for handler, formatter in formatters:
            handler.setFormatter(formatter)
        if previous is not None:
            signal.signal(signal.SIGTERM, previous)
        if prev_int is not None:
            signal.signal(signal.SIGINT, prev_int)
        if interrupted:
            # Interrupted by a signal, running as the program: every guarded output was
            # removed on the way here, and once the traceback is freed (the collection
            # closes generators left in cycles) the local worker pools have stopped their
            # workers.  The interpreter's teardown is skipped: at exit concurrent.futures
            # wakes each pool's manager thread without its lock (CPython 3.11) and, racing
            # a manager that was closing, printed "OSError: Bad file descriptor" after the
            # message (seen in CI, about 1 run in 3 of
            # tests/test_hardening.py::test_mc_workers_end_with_the_parent_on_sigterm_and_ctrl_c)
            import gc

            gc.collect()
            _exit_now(130)


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
