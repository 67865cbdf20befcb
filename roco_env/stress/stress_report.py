"""What a search found: the worst scenarios as YAML, the objective over trials (PNG),
the parameters that matter, one report section and one summary line per search.

Files in a search's folder (``OUT/POLICY_OBJECTIVE/``): ``worst_1.yaml`` ..
``worst_K.yaml`` (validated scenarios; each reproduces its recorded objective with the
search's seeds and steps), ``worst.json`` (their recorded values and parameters),
``reference.yaml`` (the default scene), ``objective.png``.
"""

from __future__ import annotations

import dataclasses
import importlib.util
import json
import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from roco_env.scenario import load_scenario, save_scenario
from roco_env.stress.objectives import Evaluation, Infeasible, evaluate
from roco_env.stress.space import param_value, reference_scenario
from roco_env.stress.study import SearchSettings, import_optuna

TOP_K = 3  # worst scenarios kept per search


@dataclass(frozen=True)
class Found:
    """One worst scenario: its rank (1 = worst), trial number, recorded objective value,
    metrics and parameters, and the YAML it was written to."""

    rank: int
    trial: int
    value: float
    metrics: dict
    params: dict
    path: Path


def worst_trials(study, k: int = TOP_K) -> list:
    """The ``k`` completed trials with the largest objective (ties: earlier trial first)."""
    done = [t for t in study.get_trials(deepcopy=False) if t.value is not None
            and t.state.name == "COMPLETE"]
    return sorted(done, key=lambda t: (-t.value, t.number))[:k]


def export_worst(settings: SearchSettings, study, k: int = TOP_K) -> list[Found]:
    """Write the ``k`` worst scenarios (``worst_1.yaml`` ...) and ``worst.json``."""
    found = []
    for rank, trial in enumerate(worst_trials(study, k), start=1):
        config = load_scenario(settings.folder / trial.user_attrs["scenario"])
        config = dataclasses.replace(
            config, name=f"stress_{settings.folder.name}_worst{rank}",
            description=f"{config.description} (trial {trial.number}, {settings.objective} "
            f"{trial.value:.6g} with seeds {list(settings.seeds)}, {settings.steps} steps)")
        path = save_scenario(config, settings.folder / f"worst_{rank}.yaml")
        load_scenario(path)  # re-validated
        found.append(Found(rank, trial.number, float(trial.value),
                           dict(trial.user_attrs.get("metrics", {})), dict(trial.params), path))
    record = [{"rank": f.rank, "trial": f.trial, "value": f.value, "metrics": f.metrics,
               "params": f.params, "scenario": f.path.name, "seeds": list(settings.seeds),
               "steps": settings.steps, "policy": settings.policy,
               "objective": settings.objective} for f in found]
    (settings.folder / "worst.json").write_text(json.dumps(record, indent=2) + "\n")
    return found


def evaluate_reference(settings: SearchSettings) -> Evaluation | None:
    """The objective on the default scene (the space's base with its reference
    overrides), same seeds and steps; None when it has no objective there."""
    path = save_scenario(reference_scenario(settings.space), settings.folder / "reference.yaml")
    try:
        return evaluate(str(path), settings.policy, settings.objective, settings.seeds,
                        settings.steps)
    except Infeasible:
        return None


def plot_objective(study, path: Path, title: str) -> Path:
    """The objective of every completed trial against its number, and the running worst."""
    from matplotlib.figure import Figure

    done = sorted((t for t in study.get_trials(deepcopy=False) if t.state.name == "COMPLETE"),
                  key=lambda t: t.number)
    numbers = [t.number for t in done]
    values = [t.value for t in done]
    running, worst = [], -math.inf
    for value in values:
        worst = max(worst, value)
        running.append(worst)
    fig = Figure(figsize=(6.4, 3.6), layout="constrained")
    ax = fig.add_subplot()
    ax.plot(numbers, values, "o", ms=3, alpha=0.6, label="trial")
    ax.step(numbers, running, where="post", color="C3", label="worst so far")
    ax.set_xlabel("trial")
    ax.set_ylabel("objective (larger = worse for the policy)")
    ax.set_title(title)
    ax.legend(loc="lower right")
    fig.savefig(path, dpi=110)
    return path


def importances(study) -> tuple[dict[str, float], str]:
    """(parameter -> importance, how it was computed): fANOVA when scikit-learn is
    installed, else PED-ANOVA (Optuna's evaluators); ``{}`` and the reason when the
    study is too small or the evaluator fails."""
    optuna = import_optuna()
    if importlib.util.find_spec("sklearn") is not None:
        evaluator, name = optuna.importance.FanovaImportanceEvaluator(seed=0), "fANOVA"
    else:
        evaluator = optuna.importance.PedAnovaImportanceEvaluator()
        name = "PED-ANOVA (fANOVA needs scikit-learn, not installed)"
    try:
        return dict(optuna.importance.get_param_importances(study, evaluator=evaluator)), name
    except (ValueError, RuntimeError) as exc:
        return {}, f"{name}: not computed ({exc})"


def _fmt(value: Any) -> str:
    if isinstance(value, float):
        return "n/a" if not math.isfinite(value) else f"{value:.3g}"
    return str(value)


def _metric_cells(metrics: dict) -> list[str]:
    return [_fmt(100 * metrics.get(k, math.nan)) for k in ("harm", "success1", "ap70")]


def section(settings: SearchSettings, study, found: list[Found],
            reference: Evaluation | None, gif: str | None = None) -> tuple[str, str]:
    """(markdown section, one-line summary) of one search."""
    folder = settings.folder
    plot = plot_objective(study, folder / "objective.png", settings.study_name)
    ranked, how = importances(study)
    names = settings.space.names
    completed = sum(t.state.name == "COMPLETE" for t in study.get_trials(deepcopy=False))
    failed = sum(t.state.name == "FAIL" for t in study.get_trials(deepcopy=False))
    head = ["scene", "trial", settings.objective, "harm %", "Success@1m1deg %", "AP@0.7 %"]
    lines = [f"## {settings.policy}: objective `{settings.objective}`", "",
             f"{completed} completed evaluations ({failed} failed or infeasible), seeds "
             f"{list(settings.seeds)}, {settings.steps} steps each, sampler {settings.sampler} "
             f"(seed {settings.seed}). Larger objective = worse for the policy.", "",
             "| " + " | ".join(head + names) + " |", "|" + "---|" * (len(head) + len(names))]
    ref_metrics = reference.metrics if reference else {}
    ref_config = reference_scenario(settings.space)
    lines.append("| " + " | ".join(
        ["default (reference.yaml)", "-", _fmt(reference.value if reference else math.nan)]
        + _metric_cells(ref_metrics) + [_fmt(param_value(ref_config, n)) for n in names]) + " |")
    for f in found:
        lines.append("| " + " | ".join(
            [f"[worst_{f.rank}]({folder.name}/{f.path.name})", str(f.trial), _fmt(f.value)]
            + _metric_cells(f.metrics) + [_fmt(f.params.get(n)) for n in names]) + " |")
    lines += ["", f"Objective over trials: ![objective]({folder.name}/{plot.name})", "",
              f"Parameter importance ({how}):", ""]
    lines += [f"- `{k}`: {v:.3f}" for k, v in ranked.items()] or ["- none"]
    if gif:
        lines += ["", f"Worst episode (worst_1, seed {settings.seeds[0]}): "
                  f"![worst episode]({Path(gif).relative_to(settings.out)})"]
    lines.append("")
    top = next(iter(ranked), "n/a")
    if found:
        worst = found[0]
        summary = (f"{settings.policy} [{settings.objective}]: worst {worst.value:.3g} (trial "
                   f"{worst.trial}, {folder.name}/{worst.path.name}) vs default "
                   f"{_fmt(reference.value if reference else math.nan)}; most important "
                   f"parameter: {top}")
    else:
        summary = f"{settings.policy} [{settings.objective}]: no completed evaluation"
    return "\n".join(lines), summary


def write_report(out: str | Path, sections: list[str], summaries: list[str]) -> Path:
    """``OUT/report.md``: the summary lines, then each search's section."""
    path = Path(out) / "report.md"
    text = ["# roco-env stress: the scenarios where each aligner breaks", "",
            *[f"- {s}" for s in summaries], "", *sections]
    path.write_text("\n".join(text))
    return path
