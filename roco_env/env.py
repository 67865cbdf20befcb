"""The PettingZoo environment (DESIGN.md section 9): glue between the stages, nothing more.

Stages (each in its own module): traffic -> pose noise -> sensing -> messages
(:mod:`roco_env.pipeline`) -> the agents' actions -> fusion (:mod:`roco_env.fusion`)
-> metrics (:mod:`roco_env.evaluation`), observations packed by
:mod:`roco_env.observation`, pictures by :mod:`roco_env.render`.

Step t: the action corrects the observation returned at t-1 (one (dx, dy, dyaw)
correction per collaborator slot, ``T_corrected = SE2(action) * T_reported``);
each evaluated agent's detections are fused with the corrected poses and scored
on that frame; then the traffic advances and the new observations are produced.
Action bounds: |dx|, |dy| <= 2 x ``agents.comm_range`` m (any pair within comm
range needs less), |dyaw| <= pi; finite values outside are applied as given,
NaN/inf or a wrong shape raise ValueError. Empty slots ignore their action.

Late fusion drops every box that overlaps the ego's own vehicle (BEV IoU with
its footprint above ``fusion.nms_iou``; CAV egos only, RSUs have no
footprint): collaborators detect the ego's car, the ground truth leaves it out
(DESIGN.md section 8), so those boxes could only be false positives (see
:mod:`roco_env.fusion.late`). With the ideal detector and clean poses the fused
AP is then exactly 1 wherever every ground-truth object is detected.

Every agent is an ego for its own fused perception. ``agents.evaluated`` (a
scenario field) may restrict which agents are scored: the others still get
observations and act, but their reward is always 0 and their info has no
AP/frame/box entries (``info["evaluated"]`` is False).

Rewards (``evaluation.reward``, override ``reward=``): ``ap70`` (default),
``ap50``, ``ap30`` = the per-step AP of the agent's fused detections at that
IoU, a NaN AP (no GT and no predictions) counting as 0; ``neg_rpe`` = minus the
mean (translation m + rotation deg) error of the corrected relative poses.

Info after a step, per agent: ``ap30/ap50/ap70`` (NaN rule above), ``rpe_before``
/ ``rpe_after`` (N, 2) [m, deg] by slot of the evaluated frame (NaN rows for
empty slots), ``n_gt``, ``n_pred``, ``frame_scores`` (P,), ``frame_tp`` /
``frame_fp`` (3, P), ``frame_n_gt`` (the exact :meth:`APAccumulator.add_stats`
input), ``fused_boxes`` (P, 7) / ``fused_scores`` (P,) / ``gt_boxes`` (G, 7)
(ego's true frame), ``evaluated``, ``evaluated_collaborators`` (agent ids by slot
of the evaluated frame) and, describing the observation returned with the
info: ``collaborators`` (agent ids by slot), ``n_collaborators`` and
``privileged`` (true/reported relative poses (N, 3) float64, object ids of the
observed boxes, -1 = false positive or empty). reset() infos carry the last
three and ``evaluated``.

Fusion (``fusion=``): ``late`` merges the boxes of the ego and its
collaborators (moved with the corrected poses) and suppresses duplicates;
``intermediate`` (needs ``detector="learned"``) warps the collaborators'
encoder maps into the ego frame with the corrected poses, max-fuses them with
the ego's on a canvas covering the evaluation range and decodes the fused map (:mod:`roco_env.fusion.intermediate`); AP
and reward then come from those decoded boxes (own footprint kept clear the same way).

The environment has no terminal state; ``max_cycles`` steps truncate the
episode, after which ``agents`` is empty and ``step`` raises until ``reset``.
``seed`` makes whole episodes reproducible; ``reset()`` without a seed starts
the next episode of the last seeded sequence.
"""

from __future__ import annotations

import os
import sys
import types
from collections.abc import Mapping, Sequence
from typing import Any

import gymnasium
import numpy as np
from pettingzoo import AECEnv, ParallelEnv
from pettingzoo.utils.conversions import parallel_to_aec

from roco_env.evaluation import evaluate_egos, metric_info, reward, slot_errors
from roco_env.fusion import FusedDetections, merge_many, suppress
from roco_env.observation import (
    EgoView,
    action_space,
    check_action,
    observation_space,
    pack_observation,
    privileged_truth,
)
from roco_env.pipeline import PerceptionFrame, Pipeline, StageClock
from roco_env.policies.base import apply_correction
from roco_env.scenario import ScenarioConfig, apply_overrides, load_scenario

RENDER_MODES = ("rgb_array", "human")


class CollabPerceptionEnv(ParallelEnv):
    """Collaborative perception under pose noise; see the module docstring for the contract.

    scenario: a scenario name from ``roco_env.list_scenarios()``, a YAML path, or a
    :class:`ScenarioConfig`; overrides: validated scenario overrides (``sigma_t=0.4``,
    ``"traffic.min_gap"``-style dotted names via ``**{...}``); frames: your own scene
    (a sequence of :class:`roco_env.traffic.frames.Frame`) with
    ``**{"traffic.source": "frames"}``.
    """

    metadata = {
        "name": "roco_collab_perception_v0",
        "render_modes": list(RENDER_MODES),
        "is_parallelizable": True,
        "render_fps": 10,
    }

    def __init__(self, scenario: str | os.PathLike | ScenarioConfig = "urban_intersection",
                 max_cycles: int = 100, render_mode: str | None = None,
                 frames: Sequence | None = None, **overrides: Any) -> None:
        if render_mode is not None and render_mode not in RENDER_MODES:
            raise ValueError(f"render_mode must be None or one of {list(RENDER_MODES)}; "
                             f"got {render_mode!r}")
        if isinstance(max_cycles, bool) or not isinstance(max_cycles, (int, np.integer)) \
                or max_cycles < 1:
            raise ValueError(f"max_cycles must be an integer >= 1; got {max_cycles!r}")
        if isinstance(scenario, ScenarioConfig):
            config = apply_overrides(scenario, overrides)
        else:
            config = load_scenario(scenario, **overrides)
        self.config = config
        self.max_cycles = int(max_cycles)
        self.render_mode = render_mode
        self.metadata = {**self.metadata, "render_fps": max(1, round(1.0 / config.traffic.dt))}
        self.clock = StageClock()
        self.pipeline = Pipeline(config, self.clock, frames)
        self.possible_agents = list(self.pipeline.agent_ids)
        self.evaluated_agents = _evaluated_agents(config, self.possible_agents)
        n, k = config.max_collaborators, config.max_boxes
        feature_shape = self.pipeline.feature_shape
        self._observation_spaces = {
            a: observation_space(k, n, feature_shape) for a in self.possible_agents}
        self._action_spaces = {
            a: action_space(n, 2.0 * config.agents.comm_range) for a in self.possible_agents}
        self.agents: list[str] = []
        self._seeds: np.random.Generator | None = None
        self._frame: PerceptionFrame | None = None
        self._shown: tuple[PerceptionFrame, dict] | None = None
        self._cycles = 0
        self._viewer = None

    def observation_space(self, agent: str) -> gymnasium.spaces.Dict:
        return self._observation_spaces[self._known(agent)]

    def action_space(self, agent: str) -> gymnasium.spaces.Box:
        return self._action_spaces[self._known(agent)]

    def reset(self, seed: int | None = None,
              options: dict | None = None) -> tuple[dict[str, dict], dict[str, dict]]:
        """Start an episode. ``options`` is accepted for API compatibility and unused."""
        if seed is not None or self._seeds is None:
            self._seeds = np.random.default_rng(seed)
        (episode_rng,) = self._seeds.spawn(1)
        self._frame = self.pipeline.reset(episode_rng)
        self._shown = None
        self._cycles = 0
        self.agents = list(self.possible_agents)
        observations = self._observations(self._frame)
        infos = {a: {"evaluated": a in self.evaluated_agents, **self._view_info(view)}
                 for a, view in zip(self.possible_agents, self._frame.views, strict=True)}
        if self.render_mode == "human":
            self.render()
        return observations, infos

    def step(self, actions: Mapping[str, Any]) -> tuple[dict, dict, dict, dict, dict]:
        """Apply the corrections, score the fused detections, advance the world."""
        checked = self._check_actions(actions)
        frame = self._frame
        corrected = {
            agent: apply_correction(view.reported_relative,
                                    checked[agent][: len(view.collaborators)])
            for agent, view in zip(self.possible_agents, frame.views, strict=True)
        }
        fused_by_agent = self._fuse(frame, corrected)
        rewards, infos = self._score(frame, corrected, fused_by_agent)
        self._shown = (frame, fused_by_agent)
        self._cycles += 1
        self._frame = self.pipeline.advance()
        observations = self._observations(self._frame)
        for agent, view in zip(self.possible_agents, self._frame.views, strict=True):
            infos[agent].update(self._view_info(view))
        truncated = self._cycles >= self.max_cycles
        terminations = dict.fromkeys(self.agents, False)
        truncations = dict.fromkeys(self.agents, truncated)
        if truncated:
            self.agents = []
        if self.render_mode == "human":
            self.render()
        return observations, rewards, terminations, truncations, infos

    def render(self) -> np.ndarray | None:
        """BEV picture (H, W, 3) uint8 in ``rgb_array`` mode; shown in a window in ``human``.

        ``human`` also renders after every reset/step. Without an interactive
        matplotlib backend (no display) it warns once and draws nothing.
        """
        if self.render_mode is None:
            gymnasium.logger.warn("render() called without a render_mode; pass "
                                  "render_mode='rgb_array' or 'human' to the constructor")
            return None
        if self._frame is None:
            raise ValueError("render() called before reset()")
        from roco_env import render as rendering

        if self.render_mode == "human":
            if self._viewer is None:
                self._viewer = rendering.HumanViewer(self.metadata["render_fps"])
            if not self._viewer.interactive:
                return None
        frame, fused = self._shown if self._shown is not None else (self._frame, {})
        ego = self.evaluated_agents[0]
        image = rendering.render_bev(frame, self.possible_agents.index(ego), fused.get(ego),
                                     title=f"step {self._cycles}  ego {ego}")
        if self.render_mode == "rgb_array":
            return image
        self._viewer.show(image)
        return None

    def close(self) -> None:
        if self._viewer is not None:
            self._viewer.close()
            self._viewer = None

    def _known(self, agent: str) -> str:
        if agent not in self._observation_spaces:
            raise ValueError(f"unknown agent {agent!r}; agents: {self.possible_agents}")
        return agent

    def _check_actions(self, actions: Mapping[str, Any]) -> dict[str, np.ndarray]:
        if not self.agents:
            raise ValueError("step() called with no live agents: the episode ended (all agents "
                             "truncated) or reset() was never called; call reset() first")
        if not isinstance(actions, Mapping):
            raise ValueError(f"actions must be a dict agent id -> (N, 3) array; "
                             f"got {type(actions).__name__}")
        unknown = sorted(set(actions) - set(self.agents), key=str)
        if unknown:
            raise ValueError(f"actions has unknown agent key(s) {unknown}; agents: {self.agents}")
        missing = [a for a in self.agents if a not in actions]
        if missing:
            raise ValueError(f"actions is missing agent(s) {missing}; give an (N, 3) action for "
                             f"every agent in env.agents (zeros = trust the reported poses)")
        n = self.config.max_collaborators
        return {a: check_action(actions[a], a, n) for a in self.agents}

    def _observations(self, frame: PerceptionFrame) -> dict[str, dict[str, np.ndarray]]:
        cfg = self.config
        with self.clock.measure("observation"):
            return {a: pack_observation(view, cfg.max_boxes, cfg.max_collaborators,
                                        cfg.features.enabled)
                    for a, view in zip(self.possible_agents, frame.views, strict=True)}

    def _view_info(self, view: EgoView) -> dict:
        collaborators = [self.possible_agents[j] for j in view.collaborators]
        return {
            "collaborators": collaborators,
            "n_collaborators": len(collaborators),
            "privileged": privileged_truth(view, self.config.max_boxes,
                                           self.config.max_collaborators),
        }

    def _score(self, frame: PerceptionFrame, corrected: dict[str, np.ndarray],
               fused: dict[str, FusedDetections]) -> tuple[dict, dict]:
        """Rewards and metric infos of every agent (evaluated ones are those in ``fused``)."""
        cfg = self.config
        views = dict(zip(self.possible_agents, frame.views, strict=True))
        rewards, infos = {}, {}
        with self.clock.measure("metrics"):
            evaluations = evaluate_egos(
                [views[a] for a in fused], list(fused.values()), [corrected[a] for a in fused],
                frame.state, frame.visibility.visible, cfg.evaluation.x_range,
                cfg.evaluation.y_range, cfg.max_collaborators)
            for agent, evaluation in zip(fused, evaluations, strict=True):
                infos[agent] = metric_info(evaluation)
                rewards[agent] = reward(evaluation, cfg.evaluation.reward)
            others = [a for a in self.possible_agents if a not in fused]
            for agent, (before, after) in zip(others, slot_errors(
                    [views[a] for a in others], [corrected[a] for a in others],
                    cfg.max_collaborators), strict=True):
                infos[agent], rewards[agent] = {"rpe_before": before, "rpe_after": after}, 0.0
        for agent, view in views.items():
            infos[agent]["evaluated"] = agent in fused
            infos[agent]["evaluated_collaborators"] = [self.possible_agents[j]
                                                       for j in view.collaborators]
        return ({a: rewards[a] for a in self.possible_agents},
                {a: infos[a] for a in self.possible_agents})

    def _fuse(self, frame: PerceptionFrame, corrected: dict[str, np.ndarray]) -> dict:
        """Fused detections of every evaluated agent (one batched NMS), own footprint clear."""
        with self.clock.measure("fusion"):
            egos = [k for k, agent in enumerate(self.possible_agents)
                    if agent in self.evaluated_agents]
            if self.config.fusion.method == "intermediate":
                from roco_env.fusion.intermediate import intermediate_fusion

                merged = intermediate_fusion(
                    self.pipeline.detector, frame.encoder_maps, frame.state, egos,
                    [frame.views[k].collaborators for k in egos],
                    [corrected[self.possible_agents[k]] for k in egos],
                    self.config.evaluation.x_range, self.config.evaluation.y_range)
            else:
                merged = merge_many([
                    (frame.views[k].boxes, frame.views[k].scores, frame.views[k].collab_boxes,
                     frame.views[k].collab_scores, corrected[self.possible_agents[k]])
                    for k in egos
                ])
            fused = suppress(merged, self.config.fusion.nms_iou,
                             [frame.footprints[k] for k in egos])
            return dict(zip(self.evaluated_agents, fused, strict=True))


def _evaluated_agents(config: ScenarioConfig, agents: list[str]) -> list[str]:
    chosen = config.agents.evaluated
    if chosen is None:
        return list(agents)
    unknown = [a for a in chosen if a not in agents]
    if unknown or not chosen:
        raise ValueError(f"agents.evaluated must be a non-empty list of agent ids from {agents}; "
                         f"got {chosen!r}")
    return [a for a in agents if a in chosen]


def parallel_env(scenario: str | os.PathLike | ScenarioConfig = "urban_intersection",
                 max_cycles: int = 100, render_mode: str | None = None,
                 **overrides: Any) -> CollabPerceptionEnv:
    """The PettingZoo ParallelEnv (see :class:`CollabPerceptionEnv`)."""
    return CollabPerceptionEnv(scenario, max_cycles=max_cycles, render_mode=render_mode,
                               **overrides)


def aec_env(scenario: str | os.PathLike | ScenarioConfig = "urban_intersection",
            max_cycles: int = 100, render_mode: str | None = None, **overrides: Any) -> AECEnv:
    """The AEC version: ``parallel_to_aec`` (which adds PettingZoo's OrderEnforcingWrapper).

    No action-clipping wrapper: finite corrections outside the action bounds are
    applied as given, and the env itself rejects NaN/inf and wrong shapes.
    """
    return parallel_to_aec(parallel_env(scenario, max_cycles, render_mode, **overrides))


class _CallableModule(types.ModuleType):
    """Makes ``roco_env.env(...)`` build the AEC env although ``roco_env.env`` is this module.

    The public API (DESIGN.md section 9) calls ``roco_env.env(...)`` and the
    package layout puts the environment in ``roco_env/env.py``; Python binds the
    submodule to the package attribute ``env`` on import, so the module itself
    must be the callable.
    """

    def __call__(self, *args: Any, **kwargs: Any) -> AECEnv:
        return aec_env(*args, **kwargs)


sys.modules[__name__].__class__ = _CallableModule
