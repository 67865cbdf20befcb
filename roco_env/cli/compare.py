"""``roco-env compare``: sweep policies x noise x density x any scenario field x seeds,
then tables and plots.

Results go to ``OUT/results.jsonl`` as cells finish; re-running the same command
resumes (finished cells are skipped, failed ones retried, and results produced by
other code, scenario content or input files are recomputed, which the run says). The report
(``report.md``, ``summary.csv``, PNG plots) is rewritten from all current results
in the folder, including earlier runs' other policies or settings.
SIGTERM or Ctrl-C stops the sweep and its workers with one line; re-running the
command resumes. One sweep at a time writes an output folder: a second compare into
a folder another one is writing stops at once with a message naming it.
Exit code 0 when every cell succeeded, 1 when some failed (listed in the report),
2 for bad options or a busy output folder, 128 + the signal number when stopped.
"""

from __future__ import annotations

import argparse
import signal
import sys
from pathlib import Path

from roco_env.sweeps.backends import BACKENDS, check_backend
from roco_env.sweeps.cells import Cell, build_grid, validate_grid
from roco_env.sweeps.options import DEFAULT_SCENARIO
from roco_env.sweeps.provenance import Provenance
from roco_env.sweeps.store import ResultsInUse
from roco_env.sweeps.sweep import SweepStopped, run_sweep, stored_results
from roco_env.sweeps.sweep_report import write_report
from roco_env.sweeps.text_specs import parse_grid, parse_overrides

# Defaults, and the `--demo` preset (crowded default scenario, the four built-in
# policies plus roco_antialias, three noise levels).
DEFAULTS = {"scenario": [DEFAULT_SCENARIO], "policies": ["identity", "coalign", "roco", "oracle"],
            "noise": [0.0, 0.4, 0.8], "density": [None], "seeds": 2, "steps": 20,
            "out": "runs/compare"}
DEMO = {**DEFAULTS, "policies": ["identity", "coalign", "roco", "roco_antialias", "oracle"],
        "seeds": 3, "steps": 40, "out": "runs/demo"}


def _setting(args: argparse.Namespace, name: str):
    given = getattr(args, name)
    if given is not None:
        return given
    return (DEMO if args.demo else DEFAULTS)[name]


def grid_from_args(args: argparse.Namespace) -> list[Cell]:
    """The sweep's cells from parsed options (defaults or the --demo preset filled in)."""
    seeds = _setting(args, "seeds")
    if seeds < 1:
        raise ValueError(f"--seeds must be >= 1 (the number of seeds 0..N-1); got {seeds}")
    return build_grid(
        _setting(args, "scenario"), _setting(args, "noise"), _setting(args, "policies"),
        list(range(seeds)), _setting(args, "steps"), densities=_setting(args, "density"),
        overrides=parse_overrides(args.overrides), axes=parse_grid(args.grid))


def run(args: argparse.Namespace) -> int:
    cells = grid_from_args(args)
    validate_grid(cells)
    check_backend(args.backend, args.workers, args.address)
    out = Path(_setting(args, "out"))
    provenance = Provenance()
    try:
        outcome = run_sweep(cells, out / "results.jsonl", backend=args.backend,
                            workers=args.workers, address=args.address, progress=not args.quiet,
                            provenance=provenance)
    except ResultsInUse as busy:
        print(f"roco-env compare: error: {busy}", file=sys.stderr)
        return 2
    except SweepStopped as stop:
        print(f"roco-env compare: stopped by {stop.signal_name}; finished cells are saved in "
              f"{stop.results_path}, run the same command again to resume", file=sys.stderr)
        return 128 + int(getattr(signal, stop.signal_name))
    stored = stored_results(out / "results.jsonl", provenance)
    report = write_report(stored.records, out, title=args.title, with_plots=not args.no_plots)
    print(report.markdown)
    print(f"cells: {len(outcome.records)} ({outcome.ran} run, {outcome.skipped} resumed, "
          f"{outcome.stale} recomputed as stale, {outcome.failed} failed)")
    if len(stored.records) > len(outcome.records):
        print(f"report: {len(stored.records)} cells, including {len(stored.records) - len(outcome.records)} "
              "from earlier runs into this folder")
    if stored.stale or stored.unreadable:
        print(f"report leaves out {stored.stale} stale record(s) and {stored.unreadable} "
              "unreadable line(s) of results.jsonl")
    print("wrote: " + ", ".join(str(p) for p in [out / "results.jsonl", *report.files]))
    failed = sum(r["status"] != "ok" for r in outcome.records)
    if failed:
        print(f"roco-env compare: {failed} cell(s) failed; see {out / 'report.md'}", file=sys.stderr)
        return 1
    return 0


def register(subparsers: argparse._SubParsersAction) -> None:
    parser = subparsers.add_parser(
        "compare", help="compare alignment policies over noise levels, densities, any "
        "scenario field and seeds",
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    grid = parser.add_argument_group("grid (lists are space separated)")
    grid.add_argument("--scenario", nargs="+", metavar="NAME",
                      help=f"scenario names or YAML paths (default: {DEFAULT_SCENARIO})")
    grid.add_argument("--policies", nargs="+", metavar="SPEC",
                      help="policy specs NAME[:KEY=VALUE,...], e.g. roco roco:tau2=2 "
                      f"(default: {' '.join(DEFAULTS['policies'])})")
    grid.add_argument("--noise", nargs="+", type=float, metavar="S",
                      help="noise levels s (sigma_t = s m, sigma_r = s deg; default: "
                      f"{' '.join(map(str, DEFAULTS['noise']))})")
    grid.add_argument("--density", nargs="+", type=float, metavar="D",
                      help="traffic densities (vehicles per 100 m of lane, parking_lot: stall fill "
                      "ratio 0..1; default: scenario's)")
    grid.add_argument("--seeds", type=int, metavar="N",
                      help=f"episodes per setting, seeds 0..N-1 (default: {DEFAULTS['seeds']})")
    grid.add_argument("--steps", type=int, metavar="T",
                      help=f"env steps per episode (default: {DEFAULTS['steps']})")
    grid.add_argument("--set", dest="overrides", action="append", default=[], metavar="KEY=VALUE",
                      help="scenario override for every cell, repeatable (e.g. --set detector=ideal)")
    grid.add_argument("--grid", action="append", default=[], metavar="KEY=V1,V2,...",
                      help="a scenario field as one more axis of the grid, repeatable (e.g. "
                      "--grid comm.delay_params.delay_ms=0,100,200 --grid cavs=2,4); the "
                      "report shows AP against it")
    grid.add_argument("--demo", action="store_true",
                      help=f"preset for a quick demo: {DEMO['seeds']} seeds, {DEMO['steps']} steps, "
                      "identity/coalign/roco/roco_antialias/oracle at noise 0, 0.4, 0.8, output in runs/demo "
                      "(explicit options win)")
    execution = parser.add_argument_group("execution")
    execution.add_argument("--backend", default="local", choices=BACKENDS,
                           help="local: process pool on this machine (default); ray: Ray cluster")
    execution.add_argument("--address", default=None,
                           help="ray only: 'auto' (running cluster) or HOST:PORT / ray://HOST:PORT; "
                           "default: start a local Ray")
    execution.add_argument("--workers", type=int, default=None,
                           help="parallel processes (default: all cores; 1 = in this process)")
    output = parser.add_argument_group("output")
    output.add_argument("--out", default=None,
                        help="output folder: results.jsonl (resumable), report.md, summary.csv, "
                        "PNG plots (default: runs/compare; runs/demo with --demo)")
    output.add_argument("--title", default="Policy comparison", help="report title")
    output.add_argument("--no-plots", action="store_true", help="skip the PNG plots")
    output.add_argument("--quiet", action="store_true", help="no progress bar")
    parser.set_defaults(func=run)
