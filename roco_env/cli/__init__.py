"""The ``roco-env`` command line.

Each subcommand lives in its own module of this package and exposes
``register(subparsers)``, which adds its parser and sets ``func`` (called with
the parsed args, returning an exit code). Modules are found automatically.
"""

from __future__ import annotations

import argparse
import importlib
import os
import pkgutil
import signal
import sys

from roco_env import __version__


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="roco-env",
        description="Pose-robust collaborative perception environment: run episodes, "
        "compare alignment policies, generate stress scenarios.",
    )
    parser.add_argument("--version", action="version", version=f"roco-env {__version__}")
    subparsers = parser.add_subparsers(dest="command", metavar="COMMAND")
    for module in sorted(pkgutil.iter_modules(__path__), key=lambda m: m.name):
        importlib.import_module(f"{__name__}.{module.name}").register(subparsers)
    return parser


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    if not getattr(args, "func", None):
        parser.print_help()
        return 0
    try:
        code = int(args.func(args) or 0)
        sys.stdout.flush()  # a closed pipe shows here, not in the interpreter's exit
        return code
    except BrokenPipeError:  # the reader left (`roco-env list | head -1`): end quietly
        os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())
        return 128 + signal.SIGPIPE
    except ValueError as exc:  # validation errors: a clear message, no traceback
        print(f"roco-env {args.command}: error: {exc}", file=sys.stderr)
        return 2
    except OSError as exc:  # e.g. an output path under a file, a folder without write access
        where = f": {exc.filename}" if exc.filename else ""
        print(f"roco-env {args.command}: error: {exc.strerror or exc}{where}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
