"""Carry the shipped learned_select weights over the aligned observation's new
``age_ms`` diagnostics column (one-off; the network computes exactly what it did).

    python baselines/learned_select/add_age_column.py roco_env/policies/weights/learned_select.pt

The file was trained on ``diagnostics`` (N, 8); the column ``age_ms`` appended to every
slot's row makes it (N, 9). This inserts, at each slot's new entry, a zero input weight in
``layers.0`` and the entry's divisor in ``input_scale`` (as train-policy would compute it),
and records the new shape and this step in the metadata (``migrated``). The weights file is
read with ``weights_only=True`` and rewritten in place.
"""

from __future__ import annotations

import json
import sys

import numpy as np
import torch

from roco_env.observation_modes import DIAGNOSTICS
from roco_env.training.rl.curriculum import SCALE_CAP


def main(path: str) -> None:
    raw = torch.load(path, map_location="cpu", weights_only=True)
    metadata = json.loads(raw["metadata"])
    state = raw["state_dict"]
    old, new = len(DIAGNOSTICS) - 1, len(DIAGNOSTICS)
    offset, keys = 0, []
    for key, shape in metadata["observation"]:
        size = int(np.prod(shape))
        if key == "diagnostics":
            if list(shape[1:]) != [old]:
                raise ValueError(f"{path}: diagnostics has shape {shape}, expected (N, {old})")
            slots = shape[0]
            at = [offset + slot * old + old for slot in range(slots)]  # after each row's end
            divisor = min(abs(DIAGNOSTICS[-1][2]), SCALE_CAP)
            weight = state["layers.0.weight"].numpy()
            state["layers.0.weight"] = torch.as_tensor(np.insert(weight, at, 0.0, axis=1))
            state["input_scale"] = torch.as_tensor(
                np.insert(state["input_scale"].numpy(), at, divisor))
            shape = [slots, new]
        keys.append([key, list(shape)])
        offset += size
    metadata["observation"] = keys
    metadata["migrated"] = (f"diagnostics (N, {old}) -> (N, {new}): zero input weights for "
                            f"the appended column {DIAGNOSTICS[-1][0]!r}")
    torch.save({"state_dict": state, "metadata": json.dumps(metadata, sort_keys=True)}, path)


if __name__ == "__main__":
    main(sys.argv[1])
