"""The ``ctsplat`` command line: one subcommand per workflow step.

Each step lives in its own module under ``ctsplat.cli`` with ``register(subparsers)``, which adds
the subparser and sets ``func`` to a callable taking the parsed ``argparse.Namespace``.
"""

from __future__ import annotations

import argparse
import difflib
import errno
import importlib
import logging
import sys
from pathlib import Path
from typing import NoReturn

from ctsplat.utils import CtsplatError, Terminated, log_warnings_once, terminate_as_interrupt

# module name -> imported lazily so `ctsplat --help` stays fast and a broken optional step
# does not take the whole CLI down.
STEP_MODULES = ["data", "radiographs", "render", "train", "sfm", "analysis", "photos"]


class OneLineParser(argparse.ArgumentParser):
    """An argument parser whose errors are one line (the problem and where the usage is), not the usage block."""

    def error(self, message: str) -> NoReturn:
        self.exit(2, f"{self.prog}: error: {one_line(message)}; see `{self.prog} --help`\n")


def build_parser() -> argparse.ArgumentParser:
    from ctsplat import __version__

    parser = OneLineParser(
        prog="ctsplat",
        description="CT scans -> synthetic radiographs -> rectified radiative Gaussian splatting. "
        "Each subcommand is one workflow step; see `ctsplat COMMAND --help`.",
    )
    parser.add_argument("--version", action="version", version=f"ctsplat {__version__}")
    parser.add_argument("-v", "--verbose", action="store_true", help="debug logging")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND", required=True)
    for name in STEP_MODULES:
        importlib.import_module(f"ctsplat.cli.{name}").register(sub)
    return parser


# errno -> what to do about it, for file-system errors that reach the top level
_OS_HINTS = {
    errno.EACCES: "check the permissions or choose another path",
    errno.EPERM: "check the permissions or choose another path",
    errno.EROFS: "the file system is read-only; choose another path",
    errno.ENOTDIR: "a file stands where a folder is needed; choose another path",
    errno.EEXIST: "the path is taken, e.g. by a file where a folder is needed; choose another path",
    errno.EISDIR: "a folder stands where a file is expected; give the file's path (or move the folder if it blocks "
                  "an output)",
    errno.ENOSPC: "the disk is full; free space or choose another path",
    errno.ENOENT: "check the path",
}


def os_error_message(exc: OSError) -> str:
    """One line for a file-system error: what failed, on which path, and what to do.

    Parameters
    ----------
    exc : OSError
        The error; for a rename its second path (the destination) is the one shown.

    Returns
    -------
    str
    """
    path = exc.filename2 if exc.filename2 is not None else exc.filename
    msg = exc.strerror or str(exc) or type(exc).__name__
    if path is not None:
        msg += f": {path}"
    hint = _OS_HINTS.get(exc.errno) if exc.errno is not None else None
    return one_line(msg + (f" ({hint})" if hint else ""))


def one_line(text: str) -> str:
    """``text`` with its line breaks folded into spaces (errors are printed as a single line)."""
    return " ".join(part.strip() for part in str(text).strip().splitlines() if part.strip())


def main(argv: list[str] | None = None) -> int:
    """Run one subcommand; user errors print one line on stderr.

    Returns
    -------
    int
        0 on success, 2 for a user error (:class:`~ctsplat.utils.CtsplatError`), a file-system error
        (``OSError``: unreadable input, unwritable or blocked output path) or too little memory for the sizes asked
        for (``MemoryError``), 130 when interrupted (Ctrl-C), 143 when
        terminated (SIGTERM: ``kill``, a cluster's cancel or time limit). Every
        output file is written under a temporary name first, so an error leaves no half-written file.
    """
    terminate_as_interrupt()  # a killed command (SIGTERM) removes its temporary files like an interrupted one
    parser = build_parser()
    args, extra = parser.parse_known_args(argv)
    if extra:  # named by the subcommand, with what most likely went wrong
        print(f"ctsplat {args.command}: error: {_unrecognized(parser, args.command, extra)}; see "
              f"`ctsplat {args.command} --help`", file=sys.stderr)
        return 2
    logging.basicConfig(
        level=logging.DEBUG if args.verbose else logging.INFO,
        format="%(asctime)s %(levelname)s %(name)s: %(message)s",
    )
    log_warnings_once()  # warnings go through the log once, in its format
    try:
        args.func(args)
    except CtsplatError as exc:
        print(f"ctsplat {args.command}: error: {one_line(str(exc))}", file=sys.stderr)
        return 2
    except (MemoryError, RuntimeError) as exc:
        # torch.OutOfMemoryError (a GPU allocation) and torch's CPU allocator failing are RuntimeErrors; other
        # RuntimeErrors are bugs: traceback
        cpu_alloc = "DefaultCPUAllocator: can't allocate memory" in str(exc)
        if not isinstance(exc, MemoryError) and type(exc).__name__ != "OutOfMemoryError" and not cpu_alloc:
            raise
        logging.getLogger(__name__).debug("out of memory", exc_info=True)
        what = "a CPU allocation failed" if cpu_alloc else one_line(str(exc)).split(". ")[0] or "an allocation failed"
        print(f"ctsplat {args.command}: error: out of memory ({what}); choose smaller sizes (grid, size, views, "
              "image size) or run on a machine with more memory", file=sys.stderr)
        return 2
    except OSError as exc:
        logging.getLogger(__name__).debug("file-system error", exc_info=True)  # the traceback with -v
        print(f"ctsplat {args.command}: error: {os_error_message(exc)}", file=sys.stderr)
        return 2
    except KeyboardInterrupt as exc:
        again = _after_interrupt(args)
        how = "terminated" if isinstance(exc, Terminated) else "interrupted"
        print(f"ctsplat {args.command}: {how}; files are written whole or not at all: {again}", file=sys.stderr)
        return 143 if isinstance(exc, Terminated) else 130
    return 0


def _unrecognized(parser: argparse.ArgumentParser, command: str, extra: list[str]) -> str:
    """What to say about arguments no parser took: an unknown option with the closest known one; a value after an
    option, where a command with an optional positional (ingest's OUT) stopped reading positionals; too many."""
    sub = next(a for a in parser._actions if isinstance(a, argparse._SubParsersAction)).choices[command]
    option = next((e for e in extra if e.startswith("-")), None)
    if option is not None:
        name = option.split("=", 1)[0]
        close = difflib.get_close_matches(name, list(sub._option_string_actions), n=1)
        return f"unknown option {name}" + (f" (did you mean {close[0]}?)" if close else "")
    optional_positional = any(not a.option_strings and a.nargs == "?" for a in sub._actions)
    hint = " (give the positional arguments before the options)" if optional_positional else ""
    return f"unrecognized arguments: {' '.join(extra)}{hint}"


def _after_interrupt(args: argparse.Namespace) -> str:
    """What to do after Ctrl-C or SIGTERM: a training run with a checkpoint continues with ``--resume``; one
    stopped before its first checkpoint, and any other command, is run again."""
    if args.command != "train":
        return "run the command again"
    from ctsplat.training.checkpoint import list_checkpoints

    if Path(args.out).is_dir() and list_checkpoints(Path(args.out)):
        return "continue with `ctsplat train --resume`"
    return "no checkpoint was saved yet: run the command again"


if __name__ == "__main__":
    sys.exit(main())
