"""The SB3 policy's actor as a learned-policy weights file (roco_env.policies.learned).

The actor of an SB3 ``ActorCriticPolicy`` with a flatten extractor is
``mlp_extractor.policy_net`` (linear + tanh layers) then ``action_net`` (linear): exported
as ``layers.<i>`` with the curriculum's ``input_scale``; the metadata names the env modes,
the observation keys and the action space, so :class:`~roco_env.policies.learned.LearnedPolicy`
acts exactly as the SB3 policy's deterministic ``predict`` (argmax / clipped mean).
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import numpy as np
import torch
from gymnasium import spaces

from roco_env.policies.learned import FORMAT, guard_metadata
from roco_env.training.rl.config import PolicyTrainConfig
from roco_env.training.rl.curriculum import INPUT_CLIP, CurriculumEnv, env_overrides


def actor_state_dict(policy: torch.nn.Module, scale: np.ndarray) -> dict[str, torch.Tensor]:
    """``layers.<i>`` of the actor's linears (in order) plus ``input_scale``."""
    linears = [m for m in policy.mlp_extractor.policy_net if isinstance(m, torch.nn.Linear)]
    for module in policy.mlp_extractor.policy_net:
        if not isinstance(module, torch.nn.Linear | torch.nn.Tanh):
            raise ValueError(f"the actor holds a {type(module).__name__}; the learned policy "
                             "runs linear layers with tanh between them")
    linears.append(policy.action_net)
    state = {}
    for index, linear in enumerate(linears):
        state[f"layers.{index}.weight"] = linear.weight.detach().clone().cpu()
        state[f"layers.{index}.bias"] = linear.bias.detach().clone().cpu()
    state["input_scale"] = torch.as_tensor(scale, dtype=torch.float64)
    return state


def action_metadata(space: spaces.Space) -> dict[str, Any]:
    """How the network's output becomes an action (MultiDiscrete or Box)."""
    if isinstance(space, spaces.MultiDiscrete):
        return {"nvec": [int(n) for n in space.nvec]}
    if isinstance(space, spaces.Box):
        return {"shape": list(space.shape), "low": space.low.tolist(), "high": space.high.tolist()}
    raise ValueError(f"cannot export a policy for the action space {space}")


def policy_env_overrides(config: PolicyTrainConfig) -> dict[str, Any]:
    """The env modes the exported policy acts in (no reward: that is the evaluator's),
    in select mode with the training env's ``action.choices``, which its actions index."""
    overrides = env_overrides(config)
    overrides.pop("reward")
    overrides.setdefault("observation.mode", config.observation_mode)
    return overrides


def save_policy(path: Path, policy: torch.nn.Module, env: CurriculumEnv,
                config: PolicyTrainConfig, provenance: dict[str, Any]) -> None:
    """Write the weights file (``torch.save`` of tensors and a JSON text)."""
    metadata = {"format": FORMAT, "input_clip": INPUT_CLIP,
                "env_overrides": policy_env_overrides(config),
                "observation": [[key, list(shape)] for key, shape in env.keys],
                "action": action_metadata(env.action_space), **provenance}
    if env.guard is not None:  # the exported policy acts behind the rule it trained behind
        metadata["guard"] = guard_metadata(env.guard)
    path.parent.mkdir(parents=True, exist_ok=True)
    torch.save({"state_dict": actor_state_dict(policy, env.scale),
                "metadata": json.dumps(metadata, sort_keys=True)}, path)
