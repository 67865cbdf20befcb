"""roco-env stress: the space file's checks, the objectives, a tiny search's determinism,
resuming without losing or repeating an evaluation, worst scenarios that reproduce their
objective exactly, and the command's bad input."""

from __future__ import annotations

import json
import math
import socket
import subprocess
import sys

import numpy as np
import optuna
import pytest
import yaml

import roco_env
from roco_env.cli import main
from roco_env.metrics import HARM_MARGIN, harm_share
from roco_env.schema import ConfigError
from roco_env.stress.objectives import Infeasible, evaluate
from roco_env.stress.space import (
    CAR_LENGTH,
    lane_density,
    load_space,
    param_value,
    parse_space,
    scenario_for,
    suggest,
)
from roco_env.stress.stress_report import export_worst
from roco_env.stress.study import SearchSettings, count, open_study, run_search

TINY = {
    "base": "urban_intersection",
    "reference": {"noise.sigma_t": 1.0, "noise.sigma_r": 1.0},
    "parameters": {
        "traffic.layout": {"type": "categorical", "choices": ["intersection", "parking_lot"]},
        "fill": {"type": "float", "low": 0.3, "high": 1.0},
        "agents.cavs": {"type": "int", "low": 2, "high": 3},
        "noise.sigma_t": {"type": "float", "low": 0.5, "high": 3.0, "log": True},
        "noise.sigma_r": {"type": "float", "low": 0.5, "high": 3.0},
    },
}


def _settings(out, budget: int = 3, sampler: str = "tpe", seed: int = 0,
              policy: str = "coalign", objective: str = "harm", **more) -> SearchSettings:
    return SearchSettings(out=str(out), policy=policy, objective=objective, budget=budget,
                          seeds=(0,), steps=2, space=parse_space(TINY), sampler=sampler,
                          seed=seed, **more)


def _trials(study) -> list[tuple]:
    return [(t.number, t.state.name, t.params, t.value) for t in study.get_trials()]


# --- the space -------------------------------------------------------------------------

def test_the_default_space_covers_the_generator_knobs_noise_and_agents():
    space = load_space()
    assert {"traffic.layout", "fill", "traffic.min_gap", "agents.cavs", "agents.rsus",
            "agents.comm_range", "noise.model", "noise.sigma_t", "noise.sigma_r"} \
        <= set(space.names)
    layout = next(p for p in space.params if p.name == "traffic.layout")
    assert set(layout.choices) == {"intersection", "highway", "roundabout", "parking_lot",
                                   "traffic_jam"}


@pytest.mark.parametrize("layout", ["intersection", "highway", "roundabout", "parking_lot",
                                    "traffic_jam"])
def test_every_corner_of_the_default_space_is_a_valid_scenario(layout):
    space = load_space()
    for end in ("low", "high"):
        values = {p.name: p.choices[0] if p.type == "categorical" else getattr(p, end)
                  for p in space.params}
        values["traffic.layout"] = layout
        config = scenario_for(space, values, "corner")
        assert config.traffic.layout == layout
        assert config.noise.sigma_t == values["noise.sigma_t"]
        assert param_value(config, "fill") == pytest.approx(values["fill"])


def test_fill_is_the_stall_fill_on_parking_lots_and_a_share_of_lane_capacity_elsewhere():
    space = parse_space(TINY)
    base = {"agents.cavs": 2, "noise.sigma_t": 1.0, "noise.sigma_r": 1.0, "fill": 0.6}
    parking = scenario_for(space, {**base, "traffic.layout": "parking_lot"}, "p")
    assert parking.traffic.density == 0.6
    lanes = scenario_for(space, {**base, "traffic.layout": "intersection"}, "l")
    gap = lanes.traffic.min_gap
    assert lanes.traffic.density == pytest.approx(0.6 * 100 / (CAR_LENGTH + gap))
    assert lane_density(1.0, 0.0) == pytest.approx(100 / CAR_LENGTH)


def _with(name: str, spec) -> dict:
    return {**TINY, "parameters": {**TINY["parameters"], name: spec}}


@pytest.mark.parametrize("data, message", [
    (_with("traffic.bogus", {"type": "float", "low": 0, "high": 1}),
     r"unknown parameter 'traffic.bogus'; allowed: fill, .*traffic.min_gap"),
    (_with("noise.sigma_t", {"type": "float", "low": 0.1, "high": 100.0}),
     r"parameters.noise.sigma_t.high=100.0 is out of range"),
    (_with("agents.cavs", {"type": "int", "low": 4, "high": 2}),
     r"parameters.agents.cavs: low must be < high"),
    (_with("noise.sigma_r", {"type": "float", "low": 0.0, "high": 2.0, "log": True}),
     r"parameters.noise.sigma_r: a log range needs low > 0"),
    (_with("fill", {"type": "discrete", "low": 0.1, "high": 1.0}),
     r"parameters.fill.type='discrete' is not allowed; choose one of \['float', 'int', "
     r"'categorical'\]"),
    (_with("fill", {"type": "float", "low": 0.1, "high": 1.5}),
     r"parameters.fill.high=1.5 is out of range"),
    (_with("fill", {"type": "float", "lo": 0.1, "high": 1.0}),
     r"unknown key 'parameters.fill.lo'"),
    (_with("fill", {"type": "float", "high": 1.0}),
     r"parameters.fill.low is required"),
    (_with("traffic.layout", {"type": "categorical", "choices": ["intersection", "moon"]}),
     r"parameters.traffic.layout.choices='moon' is not allowed"),
    (_with("traffic.layout", {"type": "categorical"}),
     r"parameters.traffic.layout.choices must be a non-empty list"),
    (_with("agents.cavs", {"type": "float", "low": 2, "high": 4}),
     r"parameters.agents.cavs: type 'float' does not fit the field, which expects an integer"),
    (_with("agents.cavs", {"type": "int", "low": 2.5, "high": 4}),
     r"parameters.agents.cavs.low must be an integer"),
    (_with("agents.evaluated", {"type": "int", "low": 0, "high": 1}),
     r"unknown parameter 'agents.evaluated'"),
    ({**TINY, "parameters": {}}, r"parameters must name at least one parameter"),
    ({**TINY, "base": "no_such_scene"}, r"base/reference: .*no_such_scene"),
    ({**TINY, "reference": {"noise.sigma_t": -1.0}}, r"base/reference: .*noise.sigma_t"),
    ({**TINY, "bogus": 1}, r"unknown key 'bogus'"),
])
def test_space_errors_name_the_parameter_and_what_is_allowed(data, message):
    with pytest.raises(ConfigError, match=message):
        parse_space(data, where="space.yaml")


def test_a_space_file_error_names_the_file(tmp_path):
    path = tmp_path / "mine.yaml"
    path.write_text(yaml.safe_dump(_with("agents.rsus", {"type": "int", "low": 0, "high": 99})))
    with pytest.raises(ConfigError, match=rf"{path}: parameters.agents.rsus.high=99"):
        load_space(path)
    with pytest.raises(ValueError, match="no such file"):
        load_space(tmp_path / "missing.yaml")


# --- objectives ------------------------------------------------------------------------

def test_harm_counts_the_poses_made_more_than_half_a_metre_worse():
    before = np.array([[1.0, 0.0], [1.0, 0.0], [1.0, 0.0], [2.0, 0.0]])
    after = np.array([[1.6, 0.0], [1.0 + HARM_MARGIN, 0.0], [0.0, 0.0], [9.0, 5.0]])
    assert harm_share(before, after) == pytest.approx(2 / 4)
    assert math.isnan(harm_share(np.zeros((0, 2)), np.zeros((0, 2))))


def test_objectives_are_larger_where_the_policy_does_worse(tmp_path):
    """The identity policy keeps every reported pose: it harms none; the oracle's AP is
    at least the identity's, so the gap is >= 0; success and ap70 are minus the metric."""
    from roco_env.scenario import load_scenario, save_scenario

    path = save_scenario(load_scenario("urban_intersection", sigma_t=2.0, sigma_r=2.0),
                         tmp_path / "noisy.yaml")
    harm = evaluate(str(path), "identity", "harm", [0], 2)
    assert harm.value == 0.0 and harm.metrics["pairs"] > 0
    success = evaluate(str(path), "identity", "success", [0], 2)
    assert success.value == -success.metrics["success1"] and success.value < 0
    ap = evaluate(str(path), "identity", "ap70", [0], 2)
    assert ap.value == -ap.metrics["ap70"]
    gap = evaluate(str(path), "identity", "gap", [0], 2)
    assert gap.value == gap.metrics["oracle_ap70"] - gap.metrics["ap70"] > 0


def test_a_scene_without_collaborators_has_no_harm(tmp_path):
    from roco_env.scenario import load_scenario, save_scenario

    path = save_scenario(load_scenario("urban_intersection", cavs=1, rsus=0),
                         tmp_path / "alone.yaml")
    with pytest.raises(Infeasible, match="no collaborator pairs"):
        evaluate(str(path), "coalign", "harm", [0], 1)


# --- the search ------------------------------------------------------------------------

def test_a_tiny_search_with_a_fixed_seed_is_deterministic_and_its_worst_scenarios_reproduce(
        tmp_path):
    first = run_search(_settings(tmp_path / "a", budget=3))
    second = run_search(_settings(tmp_path / "b", budget=3))
    assert count(first, "COMPLETE") == 3
    assert _trials(first) == _trials(second)
    other_seed = run_search(_settings(tmp_path / "c", budget=3, seed=1))
    assert [t[2] for t in _trials(other_seed)] != [t[2] for t in _trials(first)]

    settings = _settings(tmp_path / "a", budget=3)
    found = export_worst(settings, first)
    assert [f.rank for f in found] == [1, 2, 3]
    assert [f.value for f in found] == sorted((t.value for t in first.trials), reverse=True)
    for f in found:
        env = roco_env.parallel_env(str(f.path))  # loads as a scenario file
        env.close()
        again = evaluate(str(f.path), settings.policy, settings.objective, settings.seeds,
                         settings.steps)
        assert again.value == f.value  # exactly
        assert again.metrics == f.metrics
    recorded = json.loads((settings.folder / "worst.json").read_text())
    assert [r["value"] for r in recorded] == [f.value for f in found]


def test_cmaes_sampler_runs_a_search(tmp_path):
    study = run_search(_settings(tmp_path, budget=2, sampler="cmaes"))
    assert count(study, "COMPLETE") == 2


def _dead_pid() -> int:
    process = subprocess.Popen([sys.executable, "-c", "pass"])
    process.wait()
    return process.pid


def test_an_interrupted_search_resumes_without_losing_or_repeating_an_evaluation(tmp_path):
    settings = _settings(tmp_path, budget=2)
    kept = _trials(run_search(settings))
    # a run killed mid-evaluation leaves its trial RUNNING (in a process that is gone);
    # one stopped by Ctrl-C leaves it FAIL
    study = open_study(settings)
    killed = study.ask()
    killed.set_user_attr("pid", _dead_pid())
    killed.set_user_attr("host", socket.gethostname())
    killed_params = suggest(killed, settings.space)
    stopped = study.ask()
    stopped_params = suggest(stopped, settings.space)
    study.tell(stopped, state=optuna.trial.TrialState.FAIL)

    resumed = run_search(_settings(tmp_path, budget=5))
    trials = resumed.get_trials()
    assert _trials(resumed)[:2] == kept  # the finished trials are kept as they were
    assert trials[killed.number].state.name == "FAIL"
    done = [t for t in trials if t.state.name == "COMPLETE"]
    assert len(done) == 5
    retries = {t.user_attrs["retry_of"]: t.params for t in done if "retry_of" in t.user_attrs}
    assert retries == {killed.number: killed_params, stopped.number: stopped_params}
    params = [json.dumps(t.params, sort_keys=True) for t in done]
    assert len(set(params)) == len(params)  # no evaluation ran twice
    # resuming a finished search runs nothing
    assert _trials(run_search(_settings(tmp_path, budget=5))) == _trials(resumed)


def test_a_study_refuses_to_resume_with_other_seeds_or_steps(tmp_path):
    run_search(_settings(tmp_path, budget=1))
    other = SearchSettings(**{**_settings(tmp_path).__dict__, "steps": 3})
    with pytest.raises(ValueError, match="was run with other settings"):
        run_search(other)


@pytest.mark.slow
def test_two_local_workers_share_the_study(tmp_path):
    study = run_search(_settings(tmp_path, budget=4, workers=2))
    assert 4 <= count(study, "COMPLETE") <= 5  # a trial running at the stop may finish


@pytest.mark.slow
def test_the_ray_backend_runs_the_search_on_a_local_two_cpu_ray(tmp_path):
    ray = pytest.importorskip("ray")
    try:
        study = run_search(_settings(tmp_path, budget=3, backend="ray", workers=2))
    finally:
        ray.shutdown()
    assert 3 <= count(study, "COMPLETE") <= 4


# --- the command -----------------------------------------------------------------------

def test_the_command_writes_the_worst_scenarios_report_plot_and_gif(tmp_path, capsys):
    space = tmp_path / "space.yaml"
    space.write_text(yaml.safe_dump(TINY))
    out = tmp_path / "out"
    assert main(["stress", "--policy", "coalign", "--budget", "3", "--steps", "2",
                 "--space", str(space), "--out", str(out)]) == 0
    printed = capsys.readouterr().out
    assert printed.startswith("coalign [harm]: worst ")
    folder = out / "coalign_harm"
    for name in ("worst_1.yaml", "worst_2.yaml", "worst_3.yaml", "reference.yaml",
                 "objective.png", "worst_episode.gif", "worst.json"):
        assert (folder / name).is_file(), name
    report = (out / "report.md").read_text()
    assert "| default (reference.yaml) |" in report
    assert "[worst_1](coalign_harm/worst_1.yaml)" in report
    assert "Parameter importance" in report


@pytest.mark.parametrize("argv, message", [
    (["--budget", "0"], "stress: budget=0 is out of range; allowed [1, inf)"),
    (["--steps", "0"], "stress: steps=0 is out of range; allowed [1, inf)"),
    (["--policy", "no_such_policy"], "no_such_policy"),
    (["--workers", "0"], "stress: workers=0 is out of range; allowed [1, inf)"),
    (["--address", "auto"], "--address needs --backend ray"),
    (["--space", "/no/such/space.yaml"], "no such file"),
    (["--seeds", "0", "-1"], "seed must be None or an integer >= 0; got -1"),
])
def test_bad_input_is_refused_with_a_clear_message(tmp_path, capsys, argv, message):
    args = ["stress", "--policy", "coalign", "--out", str(tmp_path / "out"), "--budget", "1",
            "--steps", "1"]
    assert main(args + argv) == 2
    assert message in capsys.readouterr().err


@pytest.mark.parametrize("argv", [["--objective", "worst"], ["--sampler", "grid"],
                                  ["--seeds", "one"], ["--backend", "dask"]])
def test_bad_choices_are_refused_by_the_parser(tmp_path, capsys, argv):
    with pytest.raises(SystemExit) as stop:
        main(["stress", "--policy", "coalign", "--out", str(tmp_path)] + argv)
    assert stop.value.code == 2
    assert "stress: error" in capsys.readouterr().err


@pytest.mark.slow
def test_a_search_killed_mid_evaluation_resumes_from_its_study(tmp_path):
    """SIGKILL of a running `roco-env stress`: the rerun keeps every finished trial, fails
    the interrupted one and evaluates its parameters once more; the budget counts
    completed trials."""
    import os
    import signal
    import time

    space = tmp_path / "space.yaml"
    space.write_text(yaml.safe_dump(TINY))
    out = tmp_path / "out"
    argv = ["stress", "--policy", "coalign", "--steps", "2", "--space", str(space),
            "--out", str(out), "--no-gif"]
    code = "import sys; from roco_env.cli import main; sys.exit(main(sys.argv[1:]))"
    process = subprocess.Popen([sys.executable, "-c", code, *argv, "--budget", "1000"],
                               env={**os.environ, "PYTHONPATH": os.getcwd()})
    settings = _settings(out)
    try:
        while True:  # until two trials are done and a third is running
            time.sleep(0.5)
            assert process.poll() is None, "the search ended before it was killed"
            if (out / "study.db").exists():
                study = open_study(settings)
                if count(study, "COMPLETE") >= 2 and count(study, "RUNNING") == 1:
                    break
    finally:
        process.send_signal(signal.SIGKILL)
        process.wait()
    before = _trials(open_study(settings))
    done_before = [t for t in before if t[1] == "COMPLETE"]
    running = [t for t in before if t[1] == "RUNNING"]
    assert main(argv + ["--budget", str(len(done_before) + 2)]) == 0
    after = open_study(settings).get_trials()
    assert [t for t in _trials(open_study(settings)) if t[0] in {d[0] for d in done_before}] \
        == done_before
    done = [t for t in after if t.state.name == "COMPLETE"]
    assert len(done) == len(done_before) + 2
    if running and len(running[0][2]) == len(settings.space.params):
        assert after[running[0][0]].state.name == "FAIL"
        assert any(t.user_attrs.get("retry_of") == running[0][0] for t in done)
    params = [json.dumps(t.params, sort_keys=True) for t in done]
    assert len(set(params)) == len(params)
