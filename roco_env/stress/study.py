"""The Optuna study of one (policy, objective) search: storage, samplers, workers, resuming.

The study lives in ``OUT/study.db`` (SQLite), one study per policy and objective
(named ``POLICY|OBJECTIVE``), with each trial's scenario in
``OUT/POLICY_OBJECTIVE/trials/trial_NNNNN.yaml``. The search maximises the objective
(:mod:`roco_env.stress.objectives`: larger is worse for the policy).

Budget and resuming: ``budget`` counts COMPLETED trials; a scenario without an
objective (:class:`~roco_env.stress.objectives.Infeasible`) is a FAIL trial that does
not count. The same command resumes: finished trials are kept; a trial interrupted by
Ctrl-C (FAIL) or by a kill (left RUNNING by a process of this host that is gone) is
marked FAIL and its parameters are queued once more, so no evaluation is lost or run
twice. With several workers, each stops once the study holds ``budget`` completed
trials, so trials already running then may finish past it (at most ``workers - 1``).

Samplers: ``tpe`` (optuna.samplers.TPESampler) and ``cmaes`` (CmaEsSampler, which
needs the ``cmaes`` package; categorical parameters, which CMA-ES cannot model, are
drawn by its independent fallback sampler, as Optuna documents). Each worker's sampler
is seeded with ``seed + 7919 * worker + finished trials``: a sequential search from a
fixed seed is reproducible, and so is its resumption.
"""

from __future__ import annotations

import os
import re
import socket
from dataclasses import dataclass, fields
from pathlib import Path
from typing import Any

from roco_env.env import check_seed
from roco_env.flags import SpecFlags
from roco_env.scenario import save_scenario
from roco_env.schema import ConfigError, check_fields, spec
from roco_env.stress.objectives import OBJECTIVES, Infeasible, evaluate
from roco_env.stress.space import SearchSpace, scenario_for, suggest
from roco_env.sweeps.text_specs import parse_policy_spec

SAMPLERS = ("tpe", "cmaes")
BACKENDS = ("local", "ray")
OPTUNA_MISSING = "roco-env stress needs Optuna: pip install 'roco-env[stress]'"
RAY_MISSING = "--backend ray needs Ray: pip install 'roco-env[ray]'"
MAX_INFEASIBLE_FACTOR = 2  # stop after max(10, 2 * budget) infeasible scenarios in one run
WHERE = "stress"


def import_optuna():
    """Optuna, imported on first use (an optional dependency)."""
    try:
        import optuna
    except ImportError as exc:
        raise ValueError(OPTUNA_MISSING) from exc
    return optuna


@dataclass(frozen=True, kw_only=True)
class SearchOptions:
    """The settings a search shares with the ``roco-env stress`` command, each declared once
    here: :class:`StressOptions` (the command's options) and :class:`SearchSettings` (one
    search) are these plus their own. Checked as constructed (every field's spec,
    :func:`~roco_env.schema.check_fields`; then the seeds' values and the address's backend).
    Noise inside the space is in m and deg."""

    objective: str = spec("harm", choices=OBJECTIVES, doc="what the search makes worst")
    budget: int = spec(100, low=1, doc="completed evaluations per policy")
    seeds: tuple[int, ...] = spec((0,), doc="episode seeds of every evaluation")
    steps: int = spec(5, low=1, doc="env steps per episode")
    out: str = spec("", doc="output folder (study.db, scenarios, report.md); re-running "
                    "resumes")
    backend: str = spec("local", choices=BACKENDS, doc="local processes or Ray tasks")
    workers: int = spec(1, low=1, doc="parallel workers sharing the study")
    address: str | None = spec(None, doc="Ray cluster address for --backend ray (none: a "
                               "local Ray)")
    sampler: str = spec("tpe", choices=SAMPLERS, doc="Optuna sampler")
    seed: int = spec(0, low=0, doc="sampler seed")

    def __post_init__(self) -> None:
        check_fields(self, WHERE)
        if not self.seeds:
            raise ConfigError(f"{WHERE}: seeds must name at least one episode seed")
        for seed in self.seeds:
            check_seed(seed)
        if self.address is not None and self.backend != "ray":
            raise ConfigError(f"{WHERE}: --address needs --backend ray")


@dataclass(frozen=True, kw_only=True)
class SearchSettings(SearchOptions):
    """Everything one search needs (plain data: process pools and Ray ship it, and a copy
    is not checked again).

    policy: a policy spec, kept in its canonical form (parsed once, here); space: the
    checked search space. Refused as constructed, besides :class:`SearchOptions`'s rules:
    an unknown policy, ``sampler="cmaes"`` without the cmaes package."""

    policy: str
    space: SearchSpace

    def __post_init__(self) -> None:
        super().__post_init__()
        object.__setattr__(self, "policy", parse_policy_spec(self.policy).label)
        if self.sampler == "cmaes":
            try:
                import cmaes  # noqa: F401 - CmaEsSampler imports it when it samples
            except ImportError as exc:
                raise ValueError("--sampler cmaes needs the cmaes package: pip install cmaes "
                                 "(or pip install 'roco-env[stress]')") from exc

    @property
    def study_name(self) -> str:
        return f"{self.policy}|{self.objective}"

    @property
    def folder(self) -> Path:
        """This search's own folder under ``out`` (trial scenarios, worst scenarios)."""
        return Path(self.out) / re.sub(r"[^A-Za-z0-9_.=-]+", "_",
                                       f"{self.policy}_{self.objective}")

    @property
    def storage_url(self) -> str:
        return f"sqlite:///{Path(self.out).resolve() / 'study.db'}"

    def identity(self) -> dict[str, Any]:
        """What a resumed study must share with the one stored (else values differ)."""
        return {"seeds": list(self.seeds), "steps": self.steps,
                "space": sorted([p.name, p.type, p.low, p.high, p.log, list(p.choices)]
                                for p in self.space.params), "base": self.space.base}


@dataclass(frozen=True, kw_only=True)
class StressOptions(SearchOptions):
    """The options of ``roco-env stress`` (docs/stress.md): :class:`SearchOptions` plus the
    command's own; its command-line options are generated from these fields (:data:`FLAGS`).
    Checked as constructed (:class:`SearchOptions`), directly or by
    :func:`~roco_env.schema.build` (``build(StressOptions, values, WHERE)``)."""

    policy: list[str] = spec([], doc="policy spec(s), one search each, e.g. roco "
                             "roco_antialias coalign")
    space: str | None = spec(None, path=True, doc="YAML file of parameter ranges (none: the "
                             "shipped default space)")
    gif: bool = spec(True, doc="a GIF of the worst episode")

    def searches(self, space: SearchSpace) -> list[SearchSettings]:
        """One search per distinct policy (canonical spec) over ``space``; every bad
        setting is refused before any search starts."""
        shared = {f.name: getattr(self, f.name) for f in fields(SearchOptions)}
        found = (SearchSettings(**shared, policy=policy, space=space) for policy in self.policy)
        return list({settings.policy: settings for settings in found}.values())


# The command line's options (roco-env stress), one per field.
FLAGS = SpecFlags(StressOptions, WHERE, required=("policy", "out"))


def make_sampler(name: str, seed: int):
    """The Optuna sampler ``name`` (see :data:`SAMPLERS`) seeded with ``seed``."""
    optuna = import_optuna()
    if name == "tpe":
        return optuna.samplers.TPESampler(seed=seed)
    if name == "cmaes":
        return optuna.samplers.CmaEsSampler(seed=seed, warn_independent_sampling=False)
    raise ValueError(f"sampler={name!r} is not allowed; choose one of {list(SAMPLERS)}")


def count(study, state_name: str) -> int:
    """Trials of ``study`` in the state ``state_name`` (COMPLETE, FAIL, RUNNING, ...)."""
    optuna = import_optuna()
    state = optuna.trial.TrialState[state_name]
    return len(study.get_trials(deepcopy=False, states=(state,)))


def open_study(settings: SearchSettings, worker: int = 0):
    """The stored study (created on first use), its sampler seeded for ``worker``."""
    optuna = import_optuna()
    optuna.logging.set_verbosity(optuna.logging.ERROR)  # infeasible trials: user attrs
    (settings.folder / "trials").mkdir(parents=True, exist_ok=True)
    probe = optuna.create_study(storage=settings.storage_url, study_name=settings.study_name,
                                direction="maximize", load_if_exists=True)
    stored = probe.user_attrs.get("identity")
    if stored is None:
        probe.set_user_attr("identity", settings.identity())
    elif {**stored, "space": sorted(stored["space"])} != settings.identity():
        raise ValueError(
            f"{settings.out}: the stored study {settings.study_name!r} was run with other "
            f"settings ({stored}); resume it with the same --seeds/--steps/--space or "
            "choose another --out")
    finished = len(probe.get_trials(deepcopy=False))
    sampler = make_sampler(settings.sampler, settings.seed + 7919 * worker + finished)
    return optuna.load_study(study_name=settings.study_name, storage=settings.storage_url,
                             sampler=sampler)


def _alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    return True


def recover_interrupted(study) -> list[int]:
    """Mark the trials a stopped run left behind as FAIL and queue their parameters once
    more; returns the numbers of the trials queued again.

    Interrupted: FAIL without an ``infeasible`` reason (Ctrl-C, a crash), or RUNNING in a
    process of this host that no longer exists (a kill). A trial is retried once."""
    optuna = import_optuna()
    state = optuna.trial.TrialState
    trials = study.get_trials(deepcopy=False)
    retried = {t.user_attrs.get("retry_of") for t in trials}
    host = socket.gethostname()
    queued = []
    for trial in trials:
        if trial.state == state.RUNNING and trial.user_attrs.get("host") == host \
                and not _alive(int(trial.user_attrs.get("pid", -1))):
            study._storage.set_trial_state_values(trial._trial_id, state.FAIL)
        elif not (trial.state == state.FAIL and "infeasible" not in trial.user_attrs):
            continue
        if trial.number in retried:
            continue
        if len(trial.params) == len(study.user_attrs["identity"]["space"]):
            study.enqueue_trial(trial.params, user_attrs={"retry_of": trial.number})
            queued.append(trial.number)
    return queued


def evaluate_trial(settings: SearchSettings, trial) -> float:
    """One evaluation: draw the parameters, write and run the scenario, return the value."""
    trial.set_user_attr("pid", os.getpid())
    trial.set_user_attr("host", socket.gethostname())
    values = suggest(trial, settings.space)
    name = f"stress_{settings.folder.name}_trial{trial.number}"
    try:
        config = scenario_for(settings.space, values, name)
        path = save_scenario(config, settings.folder / "trials" / f"trial_{trial.number:05d}.yaml")
        trial.set_user_attr("scenario", str(path.relative_to(settings.folder)))
        result = evaluate(str(path), settings.policy, settings.objective, settings.seeds,
                          settings.steps)
    except (Infeasible, ValueError) as exc:  # an unbuildable scene is infeasible, not a bug
        trial.set_user_attr("infeasible", str(exc))
        raise Infeasible(str(exc)) from exc
    trial.set_user_attr("metrics", result.metrics)
    return result.value


class _Stop:
    """Stops a worker once the study holds ``budget`` COMPLETE trials, or after too many
    infeasible scenarios in this run."""

    def __init__(self, budget: int, infeasible_start: int) -> None:
        self.budget = budget
        self.limit = infeasible_start + max(10, MAX_INFEASIBLE_FACTOR * budget)

    def __call__(self, study, trial) -> None:
        if count(study, "COMPLETE") >= self.budget:
            study.stop()
        elif count(study, "FAIL") >= self.limit:
            study.stop()


def run_worker(settings: SearchSettings, worker: int = 0) -> int:
    """Run trials of the stored study until it holds ``budget`` completed ones (or too
    many scenarios were infeasible); returns the completed count. Module-level and
    argument-only so processes and Ray can run it."""
    study = open_study(settings, worker)
    if count(study, "COMPLETE") < settings.budget:
        study.optimize(lambda trial: evaluate_trial(settings, trial),
                       callbacks=[_Stop(settings.budget, count(study, "FAIL"))],
                       catch=(Infeasible,), gc_after_trial=False)
    return count(study, "COMPLETE")


def _run_local(settings: SearchSettings) -> None:
    workers = settings.workers
    if workers == 1:
        run_worker(settings, 0)
        return
    import multiprocessing

    context = multiprocessing.get_context("spawn")
    processes = [context.Process(target=run_worker, args=(settings, i), daemon=True)
                 for i in range(workers)]
    for process in processes:
        process.start()
    try:
        for process in processes:
            process.join()
    finally:
        for process in processes:
            if process.is_alive():
                process.terminate()
    failed = [p.exitcode for p in processes if p.exitcode]
    if failed:
        raise RuntimeError(f"{len(failed)} stress worker(s) failed (exit codes {failed})")


def _run_ray(settings: SearchSettings) -> None:
    workers, address = settings.workers, settings.address
    try:
        import ray
    except ImportError as exc:
        raise ValueError(RAY_MISSING) from exc
    if not ray.is_initialized():
        ray.init(address=address, num_cpus=None if address else workers,
                 include_dashboard=False, log_to_driver=False)
    task = ray.remote(num_cpus=1)(run_worker)
    ray.get([task.remote(settings, i) for i in range(workers)])


def run_search(settings: SearchSettings):
    """Run (or resume) the search; returns the loaded study. ``settings.backend``: ``local``
    (this process, or ``settings.workers`` processes sharing the SQLite study) or ``ray``
    (``workers`` Ray tasks; ``address`` a running cluster, None starts a local one): the
    study file must be reachable from every worker (one machine or a shared file system).
    The settings were checked when they were constructed."""
    study = open_study(settings)
    recover_interrupted(study)
    if settings.backend == "ray":
        _run_ray(settings)
    else:
        _run_local(settings)
    return open_study(settings)
