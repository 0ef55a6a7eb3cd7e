"""The ``ctsplat`` command line: one subcommand per workflow step.

Each step lives in its own module under ``ctsplat.cli`` with ``register(subparsers)``, which adds
the subparser and sets ``func`` to a callable taking the parsed ``argparse.Namespace``.
"""

from __future__ import annotations

import argparse
import importlib
import logging
import sys

from ctsplat.utils import CtsplatError

# module name -> imported lazily so `ctsplat --help` stays fast and a broken optional step
# does not take the whole CLI down.
STEP_MODULES = ["data", "radiographs", "render", "train", "sfm", "analysis"]


def build_parser() -> argparse.ArgumentParser:
    from ctsplat import __version__

    parser = argparse.ArgumentParser(
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


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    logging.basicConfig(
        level=logging.DEBUG if args.verbose else logging.INFO,
        format="%(asctime)s %(levelname)s %(name)s: %(message)s",
    )
    try:
        args.func(args)
    except CtsplatError as exc:
        print(f"ctsplat {args.command}: error: {exc}", file=sys.stderr)
        return 2
    return 0


if __name__ == "__main__":
    sys.exit(main())
