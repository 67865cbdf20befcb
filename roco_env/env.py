"""The PettingZoo environment: glue between the stages, nothing more.

Stages (each in its own module): traffic -> pose noise -> sensing -> messages
(:mod:`roco_env.pipeline`) -> the agents' actions -> fusion (:mod:`roco_env.fusion`)
-> metrics (:mod:`roco_env.evaluation`), observations packed by
:mod:`roco_env.observation`, the global state by :mod:`roco_env.global_state`,
pictures by :mod:`roco_env.render`. The contract (observation, action, reward,
episode end, arguments) is the docstring of :class:`CollabPerceptionEnv`; the
design notes are in the repository's docs/ folder (docs/architecture.md).
"""

from __future__ import annotations

import copy
import os
import sys
import types
from collections.abc import Mapping, Sequence
from functools import cache, partial
from typing import Any

import gymnasium
import numpy as np
from pettingzoo import AECEnv, ParallelEnv
from pettingzoo.utils import BaseWrapper
from pettingzoo.utils.conversions import parallel_to_aec

from roco_env.action_modes import AlignerSet, Alignment, Decision, build_action_mode
from roco_env.attacks import attack_truth
from roco_env.evaluation import (
    evaluate_egos,
    info_capacity,
    make_reward,
    metric_info,
    rpe_info,
    slot_errors,
)
from roco_env.fusion import FusedDetections, make_fusion, own_detections, suppress
from roco_env.global_state import pack_state, state_space
from roco_env.observation import (
    EgoView,
    observation_space,
    pack_observation,
    privileged_truth,
)
from roco_env.observation_modes import build_observation, mode_space
from roco_env.pipeline import PerceptionFrame, Pipeline, StageClock
from roco_env.registration import ENV_ID
from roco_env.scenario import (
    ConfigError,
    ScenarioConfig,
    apply_overrides,
    load_scenario,
    scenario_from_dict,
)

# The defaults of the environment's arguments (every entry point takes them from here).
DEFAULT_SCENARIO = "urban_intersection"
DEFAULT_MAX_CYCLES = 100
RENDER_MODES = ("rgb_array", "human")
# How much each step's info carries (see the class docstring's Info section).
INFO_LEVELS = ("full", "metrics", "none")
# The per-agent entries info_level="metrics" keeps.
METRIC_INFO_KEYS = ("ap30", "ap50", "ap70", "n_gt", "n_pred", "rpe_before", "rpe_after",
                    "rejected", "evaluated", "evaluated_collaborators", "agent",
                    "collaborators", "n_collaborators")
# The network stage's entries (with it on), which info_level="metrics" keeps too.
NETWORK_INFO_KEYS = ("time", "bytes_sent", "bytes_received", "messages_lost", "compensated")
# A scenario name, a YAML path, a plain mapping (the YAML keys) or a built config.
ScenarioLike = str | os.PathLike | Mapping[str, Any] | ScenarioConfig


class CollabPerceptionEnv(ParallelEnv):
    """Collaborative perception under pose noise, as a PettingZoo ParallelEnv.

    ## Description

    Connected vehicles (``cav_0``...) and roadside units (``rsu_0``...) perceive one
    traffic scene. Each agent reports a noisy world pose and shares its 3D boxes;
    every agent is an ego that corrects the relative poses of its collaborators
    (its action), fuses their boxes with its own and is scored on the result.
    Frames, units and the noise models: docs/conventions.md; the metrics:
    docs/metrics.md; the alignment algorithms: docs/alignment.md.

    ## Observation

    A ``gymnasium.spaces.Dict`` per agent, padded to K = ``max_boxes`` box slots and
    N = ``max_collaborators`` collaborator slots (nearest collaborator first, empty
    slots zero): ``pose`` (3,) the agent's reported world pose (x m, y m, yaw rad);
    ``boxes`` (K, 7) (x, y, z, l, w, h, yaw) in the agent's own frame,
    ``uncertainty`` (K, 3) (sigma_x m, sigma_y m, sigma_yaw rad), ``scores`` (K,),
    ``box_mask`` (K,); ``collab_poses`` (N, 3) the collaborators' reported world
    poses, ``collab_rel_poses`` (N, 3) the reported ``T_{j->i}``, ``collab_mask``
    (N,); ``collab_boxes`` (N, K, 7), ``collab_uncertainty``, ``collab_scores``,
    ``collab_box_mask``, each collaborator's boxes in its own frame; ``features``
    (C, H, W) BEV maps when ``features=True``. With the network stage on (any field of the
    scenario section ``comm`` changed; docs/network.md) each slot holds the newest scan
    the agent has received from that collaborator (its boxes in the collaborator's frame
    and its reported pose, both of the scan's instant) and two entries more:
    ``collab_age`` (N,) its age in s and ``collab_new`` (N,) 1 where it arrived this step.

    ## Action

    Set by the scenario section ``action`` (:mod:`roco_env.action_modes`,
    docs/learning.md); every mode acts per collaborator slot of the observation
    returned last, and empty slots ignore their action. ``action.mode``:

    - ``correction`` (default): a ``Box`` (N, 3), one correction (dx m, dy m, dyaw rad)
      in the ego frame: ``T_corrected = SE2(action) * T_reported``. Zeros trust the
      reported poses. Bounds: |dx|, |dy| <= ``action.max_translation`` (m), |dyaw| <=
      ``action.max_rotation`` (degrees); finite values outside are applied as given;
      NaN/inf, complex or bool values and wrong shapes raise ValueError.
    - ``residual``: a ``Box`` (N, 3) in [-1, 1] (clipped), ``T = SE2(action x
      action.scale) * T_base`` on the pose the base aligner ``action.base`` computes;
      zeros are the base aligner exactly.
    - ``select``: a ``MultiDiscrete`` (N,): index k fuses the slot with the k-th of
      ``action.choices``' poses, ``len(action.choices)`` rejects the collaborator.
    - ``gate``: a ``MultiDiscrete`` (N,): 0 keeps the base aligner's pose, 1 rejects.

    A rejected collaborator is left out of fusion (late and intermediate); the ground
    truth stays the collaboration's.

    ## Reward

    ``evaluation.reward`` (override ``reward=``): ``ap70`` (default), ``ap50``,
    ``ap30``, the per-step AP of the agent's fused detections at that IoU in
    its true frame (an undefined AP, no ground truth and no predictions, counts as
    0), or
    ``ap30_gain``/``ap50_gain``/``ap70_gain``, that AP minus the AP of the agent's own
    boxes alone on the same frame (doing nothing useful scores 0, harm below 0), or
    ``neg_rpe``, minus the mean (translation m + rotation deg) error of the
    corrected relative poses. Agents outside ``agents.evaluated`` (a scenario field;
    default all) act and observe but always get 0 and no AP entries in their info.
    Late fusion drops boxes on a CAV ego's own footprint: the ground truth leaves
    the ego's car out (docs/metrics.md), so they could only be false positives.

    ## Info

    Fixed shapes and no NaN, so infos compare equal with ``==`` and vector envs
    stack them; -1 (:data:`roco_env.evaluation.UNDEFINED`) marks "undefined"
    (docs/results-you-can-trust.md). After a step, per agent: ``ap30/ap50/ap70``
    (-1 when the frame has no ground truth and no predictions), ``rpe_before`` /
    ``rpe_after`` (N, 2) [m, deg] by slot of the scored frame (-1 rows for empty
    slots), ``n_gt``, ``n_pred``, ``frame_scores`` (M,), ``frame_tp`` / ``frame_fp``
    (3, M), ``frame_n_gt``, ``fused_boxes`` (M, 7) / ``fused_scores`` (M,) with
    ``fused_mask`` (M,) (real rows first, descending score), ``gt_boxes`` (M, 7)
    with ``gt_mask`` (nearest first; ``n_gt`` is the full count) in the ego's true
    frame, where M = (N + 1) x K (:func:`roco_env.evaluation.info_capacity`;
    :func:`roco_env.evaluation.info_frame_stats` gives the exact
    :meth:`roco_env.metrics.APAccumulator.add_stats` input), ``evaluated``, ``evaluated_collaborators`` (agent ids by slot of the
    scored frame) and, describing the observation returned with it: ``agent`` (the
    agent's own id), ``collaborators`` (agent ids by slot), ``n_collaborators`` and
    ``privileged`` (true and reported relative poses (N, 3) float64, object ids of
    the observed boxes, -1 = false positive, injected or empty slot; read by ``oracle``;
    ``attacker``, whether the agent attacks, and ``collab_attackers`` (N,) bool, which
    collaborators do: the attack stage, scenario section ``attack``), and
    ``rejected`` (N,) bool by slot of the scored frame. With the network stage on, also
    ``time`` (s: the frame's time, step x dt since reset for simulated traffic),
    ``bytes_sent`` (the bytes of the messages the agent sent, one per link, lost ones
    included), ``bytes_received`` (of the messages that reached
    it) and ``messages_lost`` (of those sent to it), all of the observation's step, and
    ``compensated`` (``comm.compensation: track``: the slots' boxes are moved to now).
    ``reset()`` infos carry the last four (and the network's entries) and ``evaluated``.

    ``info_level="metrics"`` keeps only :data:`METRIC_INFO_KEYS` (the APs, counts, pose
    errors and ids) and :data:`NETWORK_INFO_KEYS`, ``"none"`` nothing; ``privileged``
    (default: only with ``"full"``) adds the privileged truth at any level (the
    ``oracle`` policy reads it).

    ## Fusion

    ``fusion="late"`` (default) merges the boxes of the ego and its collaborators
    (moved with the corrected poses) and suppresses duplicates (rotated NMS).
    ``fusion="intermediate"`` (needs ``detector="learned"``) warps the collaborators'
    encoder maps into the ego frame with the corrected poses, max-fuses them with the
    ego's (through the weights' learned fusion gate, if they hold one) on a canvas
    covering the evaluation range and decodes the fused map
    (:mod:`roco_env.fusion.intermediate`); AP and reward then come from those decoded
    boxes (the ego's own footprint kept clear the same way). docs/perception.md.
    ``fusion="none"`` keeps the ego's own boxes alone, scored against the same ground
    truth (the objects its collaboration sees): the "no fusion" reference row of
    collaborative-perception tables, which no policy's action changes.

    ## State

    ``state()`` / ``state_space``: a fixed-size float32 vector for centralised
    critics, the true and reported poses of every agent and ``max_objects`` padded
    ground-truth boxes with their mask (layout in :mod:`roco_env.global_state`).

    ## Episode end

    There is no terminal state (``terminations`` are always False); after
    ``max_cycles`` steps, or at the last frame of a replay or of the user's frames
    (each frame is scored once; the final observation is the last frame's), every
    agent is truncated, ``agents`` is empty and ``step`` raises until ``reset``. ``reset(seed=s)`` makes the whole episode reproducible;
    ``reset()`` without a seed starts the next episode of the last seeded sequence.

    ## Arguments

    - ``scenario``: a name from ``roco_env.list_scenarios()``, a YAML path, a plain
      mapping with the YAML keys, or a :class:`ScenarioConfig`.
    - ``max_cycles``: steps per episode (>= 1).
    - ``render_mode``: None, ``"rgb_array"`` (``render()`` returns an (H, W, 3) uint8
      bird's-eye picture) or ``"human"`` (a matplotlib window).
    - ``frames``: your own scene, a sequence of :class:`roco_env.traffic.frames.Frame`,
      with ``**{"traffic.source": "frames"}``.
    - ``render_ego``: the agent whose fused boxes the picture shows (default: the
      first evaluated agent); also a settable attribute. The attribute
      ``render_caption`` (default "") heads the picture's title, e.g. the policy
      (``roco-env render`` sets it); the title also names the scenario, step, ego
      and pose noise.
    - ``info_level``: ``"full"`` (default), ``"metrics"`` or ``"none"`` (see Info);
      ``privileged``: whether infos carry the privileged truth (default: with ``"full"``).
    - ``**overrides``: validated scenario fields, by alias (``sigma_t=0.4``,
      ``sigma_r``, ``noise_model``, ``density``, ``cavs``, ``rsus``, ``detector``,
      ``fusion``, ``reward``, ``features``, ``delay``, ``delay_ms``, ``loss``,
      ``loss_rate``) or dotted name (``**{"traffic.min_gap": 1.0}``); a bad key or value
      raises ValueError naming the field and the allowed values.
    """

    metadata = {
        "name": ENV_ID,  # versioned, as registered
        "render_modes": list(RENDER_MODES),
        "is_parallelizable": True,
        "render_fps": 10,
    }

    def __init__(self, scenario: ScenarioLike = DEFAULT_SCENARIO,
                 max_cycles: int = DEFAULT_MAX_CYCLES, render_mode: str | None = None,
                 frames: Sequence | None = None, render_ego: str | None = None,
                 info_level: str = "full", privileged: bool | None = None,
                 **overrides: Any) -> None:
        if info_level not in INFO_LEVELS:
            raise ValueError(f"info_level must be one of {list(INFO_LEVELS)}; got {info_level!r}")
        if privileged is not None and not isinstance(privileged, bool):
            raise ValueError(f"privileged must be None, True or False; got {privileged!r}")
        if render_mode is not None and render_mode not in RENDER_MODES:
            raise ValueError(f"render_mode must be None or one of {list(RENDER_MODES)}; "
                             f"got {render_mode!r}")
        if isinstance(max_cycles, bool) or not isinstance(max_cycles, (int, np.integer)) \
                or max_cycles < 1:
            raise ValueError(f"max_cycles must be an integer >= 1; got {max_cycles!r}")
        if isinstance(scenario, Mapping):
            scenario = scenario_from_dict(scenario)
        if isinstance(scenario, ScenarioConfig):
            config = apply_overrides(scenario, overrides)
        elif isinstance(scenario, (str, os.PathLike)):
            config = load_scenario(scenario, **overrides)
        else:
            raise ConfigError(
                "scenario must be a name from roco_env.list_scenarios(), a .yaml path, a mapping "
                f"of its keys or a ScenarioConfig; got {scenario!r} ({type(scenario).__name__})")
        if config.agents.cavs + config.agents.rsus < 1:
            raise ValueError("agents.cavs + agents.rsus must be >= 1: an env needs at least one "
                             "agent (cavs=0, rsus=0 describes traffic only)")
        self.config = config
        self.info_level = info_level
        self.privileged = info_level == "full" if privileged is None else privileged
        self.max_cycles = int(max_cycles)
        self.render_mode = render_mode
        self.metadata = {**self.metadata, "render_fps": max(1, round(1.0 / config.traffic.dt))}
        self.clock = StageClock()
        self.pipeline = Pipeline(config, self.clock, frames)
        self.fusion = make_fusion(config, self.pipeline.detector)
        self.reward = make_reward(config.evaluation)
        self.possible_agents = list(self.pipeline.agent_ids)
        self.evaluated_agents = _evaluated_agents(config, self.possible_agents)
        n, k = config.max_collaborators, config.max_boxes
        feature_shape = self.pipeline.feature_shape
        self.action_mode = build_action_mode(config.action, n, self.possible_agents)
        self._observation_spaces = {  # one space object per agent: each samples its own seed
            a: observation_space(k, n, feature_shape, self.pipeline.network is not None)
            if config.observation.mode == "raw"
            else mode_space(config.observation, k, n, self.action_mode.observed_choices)
            for a in self.possible_agents}
        # The base aligner runs on every observation when the action or observation reads it,
        # unless it is a choice the aligned observation runs anyway (select mode).
        self._base_choice = self.action_mode.choice_index(config.action.base) \
            if config.observation.mode == "aligned" else None
        self.base_aligner = AlignerSet("action.base", [config.action.base], self.possible_agents) \
            if (self.action_mode.needs_base or config.observation.mode == "aligned") \
            and self._base_choice is None else None
        self.action_mode.bind_base(self.base_aligner)  # gate mode solves again without rejects
        self._action_spaces = {a: copy.deepcopy(self.action_mode.space)
                               for a in self.possible_agents}
        self.state_space = state_space(len(self.possible_agents), config.max_objects)
        self._info_capacity = info_capacity(config.max_boxes, config.max_collaborators)
        self.render_ego = render_ego
        self.render_caption = ""
        self.agents: list[str] = []
        self._seeds: np.random.Generator | None = None
        self._frame: PerceptionFrame | None = None
        self._observations: dict[str, dict] = {}  # raw, what the env's aligners read
        self._alignments: dict[str, Alignment] = {}  # the base aligner's, by agent
        self._choices: dict[str, list[Alignment]] = {}  # select mode's, shown when aligned
        self._shown: tuple[PerceptionFrame, dict] | None = None
        self._cycles = 0
        self._viewer = None

    @property
    def render_ego(self) -> str:
        """The agent whose fused boxes ``render()`` draws (default: the first evaluated one)."""
        return self._render_ego

    @render_ego.setter
    def render_ego(self, agent: str | None) -> None:
        self._render_ego = self.evaluated_agents[0] if agent is None else self._known(agent)

    def state(self) -> np.ndarray:
        """Global state of the frame the agents observe now, for centralised critics.

        True and reported poses of every agent, the padded ground-truth boxes and
        their mask; layout in :mod:`roco_env.global_state` (``state_space`` is its Box).
        """
        if self._frame is None:
            raise ValueError("state() called before reset()")
        return pack_state(self._frame.state, self._frame.reported_poses, self.config.max_objects)

    def observation_space(self, agent: str) -> gymnasium.spaces.Dict:
        return self._observation_spaces[self._known(agent)]

    def action_space(self, agent: str) -> gymnasium.spaces.Space:
        return self._action_spaces[self._known(agent)]

    def reset(self, seed: int | None = None,
              options: dict | None = None) -> tuple[dict[str, dict], dict[str, dict]]:
        """Start an episode. ``options`` is accepted for API compatibility and unused."""
        check_seed(seed)
        if seed is not None or self._seeds is None:
            self._seeds = np.random.default_rng(seed)
        (episode_rng,) = self._seeds.spawn(1)
        self._frame = self.pipeline.reset(episode_rng)
        self.action_mode.reset()
        if self.base_aligner is not None:
            self.base_aligner.reset()
        self._shown = None
        self._cycles = 0
        self.agents = list(self.possible_agents)
        observations = self._observe(self._frame)
        infos = {a: self._lean({"evaluated": a in self.evaluated_agents,
                                **self._view_info(view, self.privileged)})
                 for a, view in zip(self.possible_agents, self._frame.views, strict=True)}
        if self.render_mode == "human":
            self.render()
        return observations, infos

    def step(self, actions: Mapping[str, Any]) -> tuple[dict, dict, dict, dict, dict]:
        """Apply the corrections, score the fused detections, advance the world."""
        checked = self._check_actions(actions)
        frame = self._frame
        decisions = {
            agent: self.action_mode.decide(
                agent, checked[agent], view, self._observations[agent],
                cache(partial(self._view_info, view, privileged=True)),  # built once, if read
                self._alignments[agent].corrected if self.action_mode.needs_base else None)
            for agent, view in zip(self.possible_agents, frame.views, strict=True)
        }
        fused_by_agent, alone_by_agent = self._fuse(frame, decisions)
        rewards, infos = self._score(frame, decisions, fused_by_agent, alone_by_agent)
        self._shown = (frame, fused_by_agent)
        self._cycles += 1
        out_of_frames = self.pipeline.finished
        if not out_of_frames:
            self._frame = self.pipeline.advance()
        observations = self._observe(self._frame)
        for agent, view in zip(self.possible_agents, self._frame.views, strict=True):
            infos[agent] = self._lean({**infos[agent], **self._view_info(view, self.privileged)})
        truncated = self._cycles >= self.max_cycles or out_of_frames
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
        ego = self.render_ego
        cfg = self.config
        title = rendering.picture_title(cfg.name, self._cycles, ego, cfg.noise, self.render_caption)
        image = rendering.render_bev(frame, self.possible_agents.index(ego), fused.get(ego), title,
                                     agent_ids=self.possible_agents,
                                     evaluation_range=(cfg.evaluation.x_range,
                                                       cfg.evaluation.y_range))
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
        return {a: self.action_mode.check(actions[a], a) for a in self.agents}

    def _observe(self, frame: PerceptionFrame) -> dict[str, dict[str, np.ndarray]]:
        """Every agent's observation of ``frame`` in ``observation.mode``. The raw ones are
        kept for the env's aligners; the base aligner, when one runs, aligns them here."""
        cfg = self.config
        views = dict(zip(self.possible_agents, frame.views, strict=True))
        with self.clock.measure("observation"):
            self._observations = {
                a: pack_observation(view, cfg.max_boxes, cfg.max_collaborators,
                                    cfg.features.enabled) for a, view in views.items()}
        if cfg.observation.mode == "aligned" and self.action_mode.observed_choices:
            with self.clock.measure("choice_alignment"):
                self._choices = {
                    a: self.action_mode.observe(a, view, self._observations[a],
                                                self._view_info(view, privileged=True))
                    for a, view in views.items()}
        if self.base_aligner is not None:
            with self.clock.measure("base_alignment"):
                self._alignments = {
                    a: self.base_aligner.align(a, 0, view, self._observations[a],
                                               self._view_info(view, privileged=True))
                    for a, view in views.items()}
        elif self._base_choice is not None:
            self._alignments = {a: self._choices[a][self._base_choice] for a in views}
        if cfg.observation.mode == "raw":
            return self._observations
        with self.clock.measure("observation"):
            return {a: self._mode_observation(a, view) for a, view in views.items()}

    def _mode_observation(self, agent: str, view: EgoView) -> dict[str, np.ndarray]:
        """``agent``'s aligned or bev observation: its collaborators' boxes moved by the pose
        its action acts on (the base aligner's in residual and gate modes, else reported)."""
        alignment = self._alignments.get(agent)
        poses = alignment.corrected if self.action_mode.needs_base else view.reported_relative
        return build_observation(self.config.observation, view, self._observations[agent],
                                 poses, alignment.result if alignment else None,
                                 alignment.corrected if alignment else None,
                                 [(c.result, c.corrected) for c in self._choices.get(agent, ())])

    def _view_info(self, view: EgoView, privileged: bool) -> dict:
        collaborators = [self.possible_agents[j] for j in view.collaborators]
        info = {
            "agent": self.possible_agents[view.agent],
            "collaborators": collaborators,
            "n_collaborators": len(collaborators),
        }
        if view.network is not None:
            info.update(view.network)
        if privileged:
            info["privileged"] = {
                **privileged_truth(view, self.config.max_boxes, self.config.max_collaborators),
                **attack_truth(self.pipeline.attack.attackers, view.agent, view.collaborators,
                               self.config.max_collaborators)}
        return info

    def _lean(self, info: dict) -> dict:
        """``info`` cut to the entries ``info_level`` keeps (the privileged truth as asked)."""
        if self.info_level == "full":
            return info
        keep = METRIC_INFO_KEYS + NETWORK_INFO_KEYS if self.info_level == "metrics" else ()
        return {k: v for k, v in info.items() if k in keep or k == "privileged"}

    def _score(self, frame: PerceptionFrame, decisions: dict[str, Decision],
               fused: dict[str, FusedDetections],
               alone: dict[str, FusedDetections]) -> tuple[dict, dict]:
        """Rewards and metric infos of every agent (evaluated ones are those in ``fused``);
        ``alone`` holds the evaluated agents' own boxes when the reward is a gain."""
        cfg = self.config
        views = dict(zip(self.possible_agents, frame.views, strict=True))
        corrected = {a: decision.corrected for a, decision in decisions.items()}
        rewards, infos = {}, {}
        with self.clock.measure("metrics"):
            def evaluate(detections: dict[str, FusedDetections]) -> list:
                return evaluate_egos(
                    [views[a] for a in detections], list(detections.values()),
                    [corrected[a] for a in detections], frame.state, frame.visibility.visible,
                    cfg.evaluation.x_range, cfg.evaluation.y_range, cfg.max_collaborators,
                    cfg.evaluation.ground_truth, cfg.evaluation.z_range)

            evaluations = evaluate(fused)
            alone_evaluations = evaluate(alone) if alone else [None] * len(evaluations)
            capacity = self._info_capacity
            for agent, evaluation, own in zip(fused, evaluations, alone_evaluations, strict=True):
                infos[agent] = metric_info(evaluation, capacity)
                rewards[agent] = self.reward(evaluation, own)
            others = [a for a in self.possible_agents if a not in fused]
            for agent, (before, after) in zip(others, slot_errors(
                    [views[a] for a in others], [corrected[a] for a in others],
                    cfg.max_collaborators), strict=True):
                infos[agent] = {"rpe_before": rpe_info(before), "rpe_after": rpe_info(after)}
                rewards[agent] = 0.0
        for agent, view in views.items():
            rejected = np.zeros(cfg.max_collaborators, dtype=bool)
            rejected[: len(view.collaborators)] = ~decisions[agent].kept
            infos[agent]["rejected"] = rejected
            infos[agent]["evaluated"] = agent in fused
            infos[agent]["evaluated_collaborators"] = [self.possible_agents[j]
                                                       for j in view.collaborators]
        return ({a: rewards[a] for a in self.possible_agents},
                {a: infos[a] for a in self.possible_agents})

    def _fuse(self, frame: PerceptionFrame,
              decisions: dict[str, Decision]) -> tuple[dict, dict]:
        """(fused, alone) detections of every evaluated agent in one batched NMS: fused by
        the fusion stage through its kept collaborators, and, when the reward needs them,
        its own boxes alone (else ``alone`` is empty). Boxes on the ego's own footprint
        are dropped, except with OpenCOOD's ground truth, which holds the ego's own car."""
        with self.clock.measure("fusion"):
            egos = [k for k, agent in enumerate(self.possible_agents)
                    if agent in self.evaluated_agents]
            kept = [decisions[self.possible_agents[k]].kept for k in egos]
            poses = [decisions[self.possible_agents[k]].corrected[keep]
                     for k, keep in zip(egos, kept, strict=True)]
            own = own_detections(frame, egos) if self.reward.needs_alone else []
            sets = self.fusion.fuse(frame, egos, kept, poses) + own
            own_car_is_truth = self.config.evaluation.ground_truth == "opencood"
            footprints = [None if own_car_is_truth else frame.footprints[k] for k in egos]
            suppressed = suppress(sets, self.config.fusion.nms_iou,
                                  footprints * (len(sets) // len(egos)))
            fused = dict(zip(self.evaluated_agents, suppressed[: len(egos)], strict=True))
            if not own:
                return fused, {}
            return fused, dict(zip(self.evaluated_agents, suppressed[len(egos):], strict=True))


def check_seed(seed: Any) -> None:
    """ValueError naming the seed unless it is None or an integer >= 0 (what ``reset`` takes)."""
    if seed is None:
        return
    if isinstance(seed, bool) or not isinstance(seed, (int, np.integer)) or seed < 0:
        raise ValueError(f"seed must be None or an integer >= 0; got {seed!r}")


def _evaluated_agents(config: ScenarioConfig, agents: list[str]) -> list[str]:
    chosen = config.agents.evaluated
    if chosen is None:
        return list(agents)
    unknown = [a for a in chosen if a not in agents]
    if unknown or not chosen:
        raise ValueError(f"agents.evaluated must be a non-empty list of agent ids from {agents}; "
                         f"got {chosen!r}")
    return [a for a in agents if a in chosen]


# PettingZoo's parallel constructor (``roco_env.parallel_env``, the registry's entry point)
# is the class itself: its arguments and their defaults are written once.
parallel_env = CollabPerceptionEnv


def aec_env(*args: Any, **kwargs: Any) -> AECEnv:
    """The AEC version (``roco_env.env``, PettingZoo's name), built from the arguments of
    :class:`CollabPerceptionEnv`: ``parallel_to_aec`` (which adds PettingZoo's
    OrderEnforcingWrapper).

    No action-clipping wrapper: finite corrections outside the action bounds are
    applied as given. Each agent's action is validated at that agent's own step
    (NaN/inf or a wrong shape raise ValueError there and the action is not
    stored, so the agent may act again and later steps are unaffected).
    """
    return _CheckedActions(parallel_to_aec(CollabPerceptionEnv(*args, **kwargs)))


class _CheckedActions(BaseWrapper):
    """Validates an AEC action when it is given, not when the last agent completes the cycle.

    ``parallel_to_aec`` only stores actions and steps the parallel env after the last
    agent, so a bad action would otherwise surface at another agent's step.
    """

    def step(self, action: Any) -> None:
        agent = self.agent_selection
        if not (self.terminations[agent] or self.truncations[agent]):
            action = self.unwrapped.action_mode.check(action, agent)
        super().step(action)


class _CallableModule(types.ModuleType):
    """This module, callable: ``roco_env.env(...)`` is :func:`aec_env` (PettingZoo's
    package-level name for the AEC constructor), while ``import roco_env.env`` and
    ``from roco_env.env import ...`` keep giving the module. A package attribute and its
    submodule share one name in Python, so the module itself answers both uses."""

    def __call__(self, *args: Any, **kwargs: Any) -> AECEnv:
        return aec_env(*args, **kwargs)


sys.modules[__name__].__class__ = _CallableModule
