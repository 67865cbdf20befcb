"""Run the micro-benchmarks: ``python -m roco_env.benchmarks [--quick] [module ...]``."""

from __future__ import annotations

import argparse
import importlib
import pkgutil

import roco_env.benchmarks as benchmarks_pkg


def main(argv: list[str] | None = None) -> None:
    available = sorted(m.name for m in pkgutil.iter_modules(benchmarks_pkg.__path__)
                       if not m.name.startswith("_"))
    parser = argparse.ArgumentParser(prog="python -m roco_env.benchmarks", description=__doc__)
    parser.add_argument("modules", nargs="*", metavar="module",
                        help=f"benchmark modules to run: {', '.join(available)} (default: all)")
    parser.add_argument("--quick", action="store_true", help="fewer repetitions")
    args = parser.parse_args(argv)
    unknown = [name for name in args.modules if name not in available]
    if unknown:
        parser.error(f"unknown benchmark module {unknown[0]!r}; available: {', '.join(available)}")
    for name in args.modules or available:
        module = importlib.import_module(f"roco_env.benchmarks.{name}")
        print(f"== {name} ==", flush=True)
        for line in module.run(quick=args.quick):
            print(line, flush=True)


if __name__ == "__main__":
    main()
