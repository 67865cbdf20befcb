"""The reproducible baseline experiments of ``baselines/`` and their runner.

    python -m roco_env.sweeps.baselines                      # all, into baselines/results/
    python -m roco_env.sweeps.baselines --only paper_protocol ablation_tau2
    python -m roco_env.sweeps.baselines --smoke              # tiny version, into runs/
    python -m roco_env.sweeps.baselines --print-commands     # the same as roco-env commands

Each experiment is one sweep (resumable) written to ``OUT/<name>/`` (results.jsonl,
report.md, summary.csv, plots). Noise level s = sigma_t s m and sigma_r s deg on
every agent (the ego included: ``noise.perturb_ego=true``), realistic detector.
"""

from __future__ import annotations

import argparse
import math
import shlex
import sys
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path

from roco_env.sweeps.backends import BACKENDS
from roco_env.sweeps.cells import Cell, build_grid, validate_grid
from roco_env.sweeps.sweep import run_sweep
from roco_env.sweeps.sweep_report import write_report
from roco_env.sweeps.text_specs import Scalar, format_scalar

PAPER_NOISE = (0.0, 0.2, 0.4, 0.6, 0.8)
BUILTIN = ("identity", "coalign", "roco", "oracle")
WITH_ANTIALIAS = ("identity", "coalign", "roco", "roco_antialias", "oracle")
ANTIALIAS_NOISE = (0.0, 0.4, 0.8, 1.2, 1.5)
ANTIALIAS_SWITCHES = ("use_hypotheses", "use_size", "use_free_space", "use_mutual_detection",
                      "use_track", "use_ambiguity")
LARGE_NOISE = (0.0, 1.0, 2.0, 3.0, 5.0, 10.0)
ROSTER = ("identity", "coalign", "roco", "ransac", "v2i_calib", "freealign", "roco_fallback",
          "oracle")
PROTOCOL = {"detector": "realistic", "noise.perturb_ego": True}
LEARNED_INTERMEDIATE = {"detector": "learned", "fusion": "intermediate"}
PAPER_TABLE1_POLICIES = ("identity", "coalign", "roco", "roco_antialias", "roco_fallback", "oracle")
# RoCo with its significance test pooled over a collaborator's frames.
ROCO_POOLED = "roco:pooled_significance=0.9999"
POOLED_POLICIES = ("coalign", "roco", ROCO_POOLED)
SMOKE = {"steps": 2, "seeds": 1, "overrides": {"cavs": 2}}
# The network stage (docs/network.md): late messages and the aligners that know it.
LATE = {"delay": "fixed"}
DELAY_POLICIES = ("identity", "roco", "compensate:base=roco")
MOTION_POLICIES = ("coalign", "roco", "compensate:base=coalign", "compensate:base=roco",
                   "compensate:base=roco,mode=static")
BUDGETS = (100, 300, 1000, 3000, 10000, 30000, 100000, 300000, 1000000)
# The realistic preset's box-centre and yaw noise (roco_env.sensing.detector.DetectorParams) times 1.5:
# clean AP@0.7 on dair_like falls to the RoCo paper's DAIR-V2X level (about 60).
DETECTOR_NOISE_X15 = {"detector.params.sigma_xy": 0.09, "detector.params.sigma_xy_per_m": 0.003,
                      "detector.params.sigma_xy_occlusion": 0.375,
                      "detector.params.sigma_yaw": 0.03, "detector.params.sigma_yaw_per_m": 0.0006,
                      "detector.params.sigma_yaw_occlusion": 0.15}


def _box_sigma(xy: float) -> dict[str, Scalar]:
    """Overrides for extra noise on the learned boxes every agent reports and shares (not on
    its feature maps): ``xy`` m on each centre axis and 5 deg per m of it on the heading
    (given in rad, 5 digits)."""
    return {"detector.params.box_sigma_xy": xy,
            "detector.params.box_sigma_yaw": round(math.radians(5.0 * xy), 5)}


# 0.3 m / 1.5 deg: the one value fitted to the RoCo paper's Table 1 losses
# (docs/paper-scenarios.md, "Calibrated box precision").
CALIBRATED_BOXES = _box_sigma(0.3)
# RoCo as the paper describes it: no do-no-harm significance test (a correction is applied
# whenever matching and the robust solve find one).
ROCO_WITHOUT_TEST = "roco:significance=null"


@dataclass(frozen=True)
class Experiment:
    """One sweep: the grid and what it answers."""

    name: str
    question: str
    scenarios: tuple[str, ...]
    noises: tuple[float, ...]
    policies: tuple[str, ...]
    seeds: int = 3
    steps: int = 40
    densities: tuple[float | None, ...] = (None,)
    overrides: dict[str, Scalar] = field(default_factory=lambda: dict(PROTOCOL))
    grid: dict[str, tuple[Scalar, ...]] = field(default_factory=dict)

    def cells(self, smoke: bool = False, seeds: int | None = None,
              steps: int | None = None) -> list[Cell]:
        """The grid; ``smoke`` keeps every axis but uses 1 seed, 2 steps and 2 CAVs;
        ``seeds``/``steps`` replace the experiment's own (a cheaper preliminary run)."""
        if smoke:
            seeds, steps = SMOKE["seeds"], SMOKE["steps"]
        seeds, steps = seeds or self.seeds, steps or self.steps
        overrides = {**self.overrides, **(SMOKE["overrides"] if smoke else {})}
        return build_grid(self.scenarios, self.noises, self.policies, list(range(seeds)), steps,
                          densities=self.densities, overrides=overrides, axes=self.grid)

    def command(self, out: str) -> str:
        """The equivalent ``roco-env compare`` command line."""
        words = ["roco-env", "compare", "--scenario", *self.scenarios,
                 "--policies", *self.policies,
                 "--noise", *(format_scalar(n) for n in self.noises),
                 "--seeds", str(self.seeds), "--steps", str(self.steps)]
        if self.densities != (None,):
            words += ["--density", *(format_scalar(float(d)) for d in self.densities)]
        for key, value in self.overrides.items():
            words += ["--set", f"{key}={format_scalar(value)}"]
        for key, values in self.grid.items():
            words += ["--grid", f"{key}={','.join(map(format_scalar, values))}"]
        words += ["--out", f"{out}/{self.name}", "--title", self.name]
        return shlex.join(words)


EXPERIMENTS: tuple[Experiment, ...] = (
    Experiment("paper_protocol", "Table 1: AP@0.5/0.7 vs noise 0-0.8 (crowded urban, highway)",
               ("crowded_intersection", "highway_dense"), PAPER_NOISE, WITH_ANTIALIAS),
    Experiment("crowding_intersection", "Crowding: AP@0.7 vs vehicles per 100 m of lane",
               ("crowded_intersection",), (0.4, 0.8), BUILTIN,
               densities=(2.0, 4.0, 6.0, 9.0, 12.0, 15.0)),
    Experiment("crowding_parking", "Crowding, repetitive: parking-lot fill ratio",
               ("parking_lot",), (0.4, 0.8), WITH_ANTIALIAS,
               densities=(0.3, 0.5, 0.7, 0.9, 1.0)),
    Experiment("ablation_tau2", "Table 2: RoCo's gate tau2 in 1..4 m (single gate, as the paper; "
               "roco = shipped, with the 6 m fallback gate)",
               ("crowded_intersection",), (0.2, 0.4, 0.6, 0.8),
               (*(f"roco:coarse_tau2=null,tau2={t}" for t in (1, 2, 3, 4)), "roco")),
    Experiment("ablation_similarity", "Table 3: distance / edge similarity (coalign = neither)",
               ("crowded_intersection",), (0.2, 0.4, 0.8),
               ("coalign", "roco:use_edge_similarity=false",
                "roco:use_distance_similarity=false", "roco")),
    Experiment("ablation_modules", "Table 4: matching and robust optimisation (coalign = neither)",
               ("crowded_intersection",), (0.2, 0.4, 0.8),
               ("coalign", "roco:robust_kernel=null", "roco:iterate=false", "roco")),
    Experiment("beyond_paper", "Beyond the paper: noise 1.0, 1.5, 2.0",
               ("crowded_intersection", "highway_dense"), (1.0, 1.5, 2.0), WITH_ANTIALIAS),
    Experiment("alignment_accuracy", "Pose accuracy: RPE, Success@1m1deg, matching P/R",
               ("urban_intersection", "parking_lot"), (0.2, 0.4, 0.6, 0.8, 1.0, 1.5),
               ("identity", "coalign", "roco"), seeds=2, steps=30),
    Experiment("antialias_parking", "Aliasing: a full parking lot, roco vs roco_antialias",
               ("parking_lot",), ANTIALIAS_NOISE, ("identity", "roco", "roco_antialias"),
               seeds=4, steps=10, densities=(1.0,)),
    Experiment("antialias_scenes", "roco_antialias on non-repetitive scenes",
               ("urban_intersection", "highway_dense", "traffic_jam"), ANTIALIAS_NOISE,
               ("identity", "roco", "roco_antialias"), seeds=2, steps=10),
    Experiment("ablation_antialias", "roco_antialias: each component switched off, full parking lot",
               ("parking_lot",), (0.8, 1.5),
               ("roco", "roco_antialias",
                *(f"roco_antialias:{switch}=false" for switch in ANTIALIAS_SWITCHES)),
               seeds=2, steps=10, densities=(1.0,)),
    Experiment("paper_protocol_intermediate",
               "Table 1 with intermediate fusion of the learned detector (noise 0-0.8)",
               ("crowded_intersection", "highway_dense"), PAPER_NOISE, BUILTIN, seeds=1, steps=10,
               overrides={**PROTOCOL, **LEARNED_INTERMEDIATE}),
    Experiment("large_noise", "Large noise 1-10 m/deg: prior-free aligners and roco_fallback",
               ("urban_intersection", "highway_dense", "v2x_crossroad"), LARGE_NOISE, ROSTER,
               seeds=2, steps=20),
    Experiment("paper_table1_late", "Table 1 in shape, late fusion: the dataset-shaped scenes",
               ("v2xset_like", "dair_like"), PAPER_NOISE, BUILTIN),
    Experiment("paper_table1_intermediate",
               "Table 1 in shape and magnitude: learned intermediate fusion, dataset-shaped scenes",
               ("v2xset_like", "dair_like"), PAPER_NOISE, PAPER_TABLE1_POLICIES, seeds=2, steps=20,
               overrides={**PROTOCOL, **LEARNED_INTERMEDIATE}),
    Experiment("paper_table1_intermediate_seeds",
               "Its losses from 0.0 to 0.8 on 6 seeds: how much the 2-seed table's loss ratios move",
               ("v2xset_like", "dair_like"), (0.0, 0.8), ("identity", "coalign", "roco"), seeds=6,
               steps=20, overrides={**PROTOCOL, **LEARNED_INTERMEDIATE}),
    Experiment("ablation_fusion_gate",
               "The same without the learned fusion gate: intermediate fusion by the plain maximum",
               ("v2xset_like", "dair_like"), PAPER_NOISE, BUILTIN, seeds=2, steps=20,
               overrides={**PROTOCOL, **LEARNED_INTERMEDIATE, "detector.params.gate": False}),
    Experiment("paper_table1_learned_late",
               "The same with late fusion of the same learned detector",
               ("v2xset_like", "dair_like"), PAPER_NOISE, BUILTIN, seeds=2, steps=20,
               overrides={**PROTOCOL, "detector": "learned"}),
    Experiment("paper_table1_no_fusion",
               "The no-fusion reference: each ego's own learned boxes, the same ground truth",
               ("v2xset_like", "dair_like"), (0.0,), ("identity",), seeds=2, steps=20,
               overrides={**PROTOCOL, "detector": "learned", "fusion": "none"}),
    Experiment("paper_table1_calibrated",
               "Table 1 with the shared boxes' precision calibrated to the paper's losses",
               ("v2xset_like", "dair_like"), PAPER_NOISE,
               (*PAPER_TABLE1_POLICIES, ROCO_WITHOUT_TEST, ROCO_POOLED), seeds=2,
               steps=20,
               overrides={**PROTOCOL, **LEARNED_INTERMEDIATE, **CALIBRATED_BOXES}),
    Experiment("paper_table1_calibrated_seeds",
               "The same on 6 seeds: its losses and the RoCo - CoAlign order at each level",
               ("v2xset_like", "dair_like"), PAPER_NOISE,
               ("identity", "coalign", "roco", ROCO_WITHOUT_TEST, ROCO_POOLED), seeds=6,
               steps=20,
               overrides={**PROTOCOL, **LEARNED_INTERMEDIATE, **CALIBRATED_BOXES}),
    *(Experiment(f"box_sigma_{xy:g}",
                 f"Sensitivity of the calibration: shared boxes' extra noise {xy:g} m",
                 ("v2xset_like", "dair_like"), (0.0, 0.8), ("identity", "coalign", "roco"),
                 seeds=2, steps=20,
                 overrides={**PROTOCOL, **LEARNED_INTERMEDIATE, **_box_sigma(xy)})
      for xy in (0.1, 0.2, 0.4)),
    Experiment("pooled_significance_late",
               "RoCo's significance test pooled over a collaborator's frames, late fusion",
               ("v2xset_like", "dair_like"), PAPER_NOISE, POOLED_POLICIES),
    Experiment("pooled_significance_intermediate",
               "The same with learned intermediate fusion",
               ("v2xset_like", "dair_like"), PAPER_NOISE, POOLED_POLICIES, seeds=2, steps=20,
               overrides={**PROTOCOL, **LEARNED_INTERMEDIATE}),
    Experiment("late_knob_nms", "Knob: late-fusion NMS at BEV IoU 0.3 instead of 0.15",
               ("dair_like",), (0.0, 0.4, 0.8), BUILTIN[:3],
               overrides={**PROTOCOL, "fusion.nms_iou": 0.3}),
    Experiment("late_knob_detector", "Knob: 1.5 x the detector's localisation noise",
               ("dair_like",), (0.0, 0.4, 0.8), BUILTIN[:3],
               overrides={**PROTOCOL, **DETECTOR_NOISE_X15}),
    Experiment("v2xvit_protocol",
               "V2X-ViT's protocol: 0.2 m / 0.2 deg pose noise and a 100 ms delay, late and "
               "learned intermediate fusion of the learned detector",
               ("v2xset_like",), (0.2,),
               ("identity", "coalign", "roco", "compensate:base=roco", "oracle"), seeds=1,
               steps=10, overrides={**PROTOCOL, "detector": "learned", **LATE},
               grid={"delay_ms": (0, 100), "fusion": ("late", "intermediate"),
                     "comm.compensation": ("none", "track")}),
    Experiment("delay_sweep",
               "AP against a fixed delay of 0-400 ms, without and with the ego's compensation",
               ("highway_dense", "v2xset_like"), (0.0,), DELAY_POLICIES, seeds=1, steps=20,
               overrides={**PROTOCOL, **LATE},
               grid={"delay_ms": (0, 100, 200, 300, 400),
                     "comm.compensation": ("none", "track")}),
    Experiment("delay_baselines",
               "Beside the delay sweep: the oracle and the ego alone (fusion none) at 0-400 ms",
               ("highway_dense", "v2xset_like"), (0.0,), ("identity", "oracle"), seeds=1,
               steps=20, overrides={**PROTOCOL, **LATE},
               grid={"delay_ms": (0, 100, 400), "fusion": ("late", "none")}),
    Experiment("delay_motion",
               "Motion read as pose error: the pose error each aligner adds at pose noise 0 "
               "and 100-300 ms, without and with compensation",
               ("highway_dense",), (0.0,), MOTION_POLICIES, seeds=1, steps=20,
               overrides={**PROTOCOL, **LATE}, grid={"delay_ms": (100, 200, 300)}),
    Experiment("loss_sweep",
               "AP against the loss rate, independent and bursty losses; the ego fusing only "
               "this step's messages (max age 50 ms) or the newest it holds (1000 ms)",
               ("v2xset_like",), (0.2,), ("identity", "roco"), seeds=2, steps=20,
               grid={"loss": ("bernoulli", "gilbert_elliott"),
                     "loss_rate": (0.0, 0.1, 0.2, 0.3, 0.5, 0.7),
                     "comm.max_age_ms": (50, 1000)}),
    Experiment("loss_limit",
               "Loss towards 1: late fusion against the no-fusion reference",
               ("v2xset_like",), (0.2,), ("identity", "roco"), seeds=2, steps=20,
               overrides={**PROTOCOL, "loss": "bernoulli"},
               grid={"loss_rate": (0.5, 0.8, 0.9, 0.95, 1.0), "comm.max_age_ms": (50, 1000),
                     "fusion": ("late", "none")}),
    Experiment("bandwidth",
               "AP against the per-link budget (bytes per message): boxes (late fusion) vs "
               "feature maps (intermediate fusion, sparse float16)",
               ("v2xset_like",), (0.0,), ("identity",), seeds=1, steps=10,
               overrides={**PROTOCOL, "detector": "learned", "comm.feature_codec": "sparse_f16"},
               grid={"comm.budget_bytes": BUDGETS, "fusion": ("late", "intermediate")}),
)


def experiment(name: str) -> Experiment:
    for item in EXPERIMENTS:
        if item.name == name:
            return item
    raise ValueError(f"unknown experiment {name!r}; available: "
                     f"{', '.join(e.name for e in EXPERIMENTS)}")


def run_experiments(names: Sequence[str], out: Path, smoke: bool = False, backend: str = "local",
                    workers: int | None = None, progress: bool = True, seeds: int | None = None,
                    steps: int | None = None) -> int:
    """Run the named experiments into ``out/<name>/``; returns the number of failed cells."""
    chosen = [experiment(n) for n in names]
    grids = {e.name: e.cells(smoke, seeds, steps) for e in chosen}
    for cells in grids.values():
        validate_grid(cells)
    failed = 0
    for item in chosen:
        print(f"== {item.name}: {item.question} ({len(grids[item.name])} cells)", flush=True)
        outcome = run_sweep(grids[item.name], out / item.name / "results.jsonl", backend=backend,
                            workers=workers, progress=progress)
        report = write_report(outcome.records, out / item.name, title=f"{item.name}: "
                              f"{item.question}")
        print(report.markdown, flush=True)
        failed += outcome.failed
    return failed


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m roco_env.sweeps.baselines",
                                     description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--only", nargs="+", metavar="NAME",
                        help=f"experiments to run (default: all: "
                        f"{' '.join(e.name for e in EXPERIMENTS)})")
    parser.add_argument("--smoke", action="store_true",
                        help="tiny version (1 seed, 2 steps, 2 CAVs) into runs/baselines_smoke")
    parser.add_argument("--seeds", type=int, default=None,
                        help="seeds per setting for every experiment (default: each one's own)")
    parser.add_argument("--steps", type=int, default=None,
                        help="steps per episode for every experiment (default: each one's own)")
    parser.add_argument("--out", default=None,
                        help="output folder (default: baselines/results, or runs/baselines_smoke)")
    parser.add_argument("--backend", default="local", choices=BACKENDS)
    parser.add_argument("--workers", type=int, default=None, help="default: all cores")
    parser.add_argument("--print-commands", action="store_true",
                        help="print the equivalent roco-env compare commands and exit")
    parser.add_argument("--quiet", action="store_true", help="no progress bar")
    args = parser.parse_args(argv)
    out = Path(args.out or ("runs/baselines_smoke" if args.smoke else "baselines/results"))
    names = args.only or [e.name for e in EXPERIMENTS]
    try:
        if args.print_commands:
            for name in names:
                print(experiment(name).command(str(out)))
            return 0
        for option in ("seeds", "steps"):
            if getattr(args, option) is not None and getattr(args, option) < 1:
                raise ValueError(f"--{option} must be >= 1; got {getattr(args, option)}")
        failed = run_experiments(names, out, args.smoke, args.backend, args.workers,
                                 not args.quiet, args.seeds, args.steps)
    except ValueError as exc:
        print(f"{parser.prog}: error: {exc}", file=sys.stderr)
        return 2
    return 1 if failed else 0


if __name__ == "__main__":
    sys.exit(main())
