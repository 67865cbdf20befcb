"""Resumable training state, written without pickle.

``OUT/checkpoint/``: ``policy.pt`` and ``optimizer.pt`` (``state_dict`` s, ``torch.save``,
read with ``weights_only=True``), ``rng.pt`` (torch's generator state and numpy's global
Mersenne-Twister key as tensors) and ``state.json`` (the config, counters, learning curve).
Each file is written to a temporary name and renamed, and ``state.json`` last, so an
interrupted save leaves the previous checkpoint readable.
"""

from __future__ import annotations

import json
import os
from dataclasses import asdict
from pathlib import Path
from typing import Any

import numpy as np
import torch

from roco_env.training.rl.config import PolicyTrainConfig

FOLDER = "checkpoint"


def _replace(path: Path, write) -> None:
    tmp = path.with_name(path.name + ".tmp")
    write(tmp)
    os.replace(tmp, path)


def save_checkpoint(out: Path, model: Any, episodes: int, state: dict[str, Any]) -> None:
    """Save the SB3 ``model``'s policy and optimizer, the RNGs and ``state`` (JSON)."""
    folder = out / FOLDER
    folder.mkdir(parents=True, exist_ok=True)
    _replace(folder / "policy.pt", lambda p: torch.save(model.policy.state_dict(), p))
    _replace(folder / "optimizer.pt",
             lambda p: torch.save(model.policy.optimizer.state_dict(), p))
    name, key, pos, has_gauss, gauss = np.random.get_state()
    rng = {"torch": torch.get_rng_state(), "numpy_key": torch.as_tensor(key.astype(np.int64)),
           "numpy_rest": torch.tensor([pos, has_gauss, 0], dtype=torch.int64),
           "numpy_gauss": torch.tensor([gauss], dtype=torch.float64)}
    _replace(folder / "rng.pt", lambda p: torch.save(rng, p))
    record = {**state, "num_timesteps": int(model.num_timesteps),
              "n_updates": int(model._n_updates), "episodes": int(episodes)}
    _replace(folder / "state.json", lambda p: p.write_text(json.dumps(record, indent=1)))


def load_state(out: Path, config: PolicyTrainConfig) -> dict[str, Any] | None:
    """The saved ``state.json`` (None when there is no checkpoint); a checkpoint of another
    config is a ValueError naming the fields that differ (``total_timesteps`` may grow: a
    longer run continues a shorter one; a field the saved config lacks, added since,
    compares as its default)."""
    path = out / FOLDER / "state.json"
    if not path.is_file():
        return None
    state = json.loads(path.read_text())
    saved, now = state.get("config", {}), asdict(config)
    if saved.get("total_timesteps", 0) > config.total_timesteps:
        raise ValueError(f"{out} holds a checkpoint of a run of total_timesteps="
                         f"{saved['total_timesteps']}; ask for at least as many")
    saved.pop("total_timesteps", None)
    now.pop("total_timesteps")
    # a field added since the checkpoint was saved compares as its default
    defaults = asdict(PolicyTrainConfig())
    saved = {**{k: v for k, v in defaults.items() if k in now}, **saved}
    differ = sorted(k for k in set(saved) | set(now) if saved.get(k) != now.get(k))
    if differ:
        raise ValueError(f"{out} holds a checkpoint of another configuration (fields "
                         f"{differ} differ: {[saved.get(k) for k in differ]} there, "
                         f"{[now.get(k) for k in differ]} now); use another --out or the "
                         "same options")
    return state


def restore_checkpoint(out: Path, model: Any, state: dict[str, Any]) -> None:
    """Load the policy, optimizer, counters and RNGs of the checkpoint into ``model``."""
    folder = out / FOLDER
    model.policy.load_state_dict(torch.load(folder / "policy.pt", weights_only=True))
    model.policy.optimizer.load_state_dict(torch.load(folder / "optimizer.pt",
                                                      weights_only=True))
    rng = torch.load(folder / "rng.pt", weights_only=True)
    torch.set_rng_state(rng["torch"])
    pos, has_gauss, _ = (int(v) for v in rng["numpy_rest"])
    np.random.set_state(("MT19937", rng["numpy_key"].numpy().astype(np.uint32), pos,
                         has_gauss, float(rng["numpy_gauss"][0])))
    model.num_timesteps = int(state["num_timesteps"])
    model._n_updates = int(state["n_updates"])
