"""Run the micro-benchmarks: ``python -m roco_env.benchmarks [--quick] [module ...]``."""

from __future__ import annotations

import argparse
import importlib
import pkgutil

import roco_env.benchmarks as benchmarks_pkg


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("modules", nargs="*", help="benchmark modules to run (default: all)")
    parser.add_argument("--quick", action="store_true", help="fewer repetitions")
    args = parser.parse_args()
    names = args.modules or sorted(
        m.name for m in pkgutil.iter_modules(benchmarks_pkg.__path__) if not m.name.startswith("_")
    )
    for name in names:
        module = importlib.import_module(f"roco_env.benchmarks.{name}")
        print(f"== {name} ==", flush=True)
        for line in module.run(quick=args.quick):
            print(line, flush=True)


if __name__ == "__main__":
    main()
