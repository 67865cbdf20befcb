"""Learned policies: a small MLP trained with PPO (``roco-env train-policy``), run by argmax.

A weights file (``torch.save`` of a plain dict, read back with ``weights_only=True``) holds

* ``state_dict``: the MLP's tensors, ``layers.<i>.weight`` / ``layers.<i>.bias`` of its
  linear layers (tanh between them, none after the last) and ``input_scale`` (F,), the
  divisor applied to the flat observation;
* ``metadata``: a JSON text with ``format`` (:data:`FORMAT`), ``input_clip`` (the
  scaled observation is clipped to +-it), ``env_overrides`` (the
  scenario fields the policy acts in: ``action.mode``, ``observation.mode``,
  ``max_collaborators``, ``max_boxes`` and the mode's aligners), ``observation`` (the
  observation keys in the flattening order with their shapes), ``action`` (``nvec`` of a
  MultiDiscrete action, or ``shape``/``low``/``high`` of a Box one) and provenance
  (``command``, training summary).

The policy flattens the observation (keys in the stored order, each raveled), divides by
``input_scale``, clips to +-``input_clip``, runs the MLP and acts deterministically: per
slot the argmax of its logits (``select``/``gate``), or the mean clipped to the bounds
(Box modes).

Two files are shipped, each registered under its name (:data:`SHIPPED`):
``learned_select`` (select over identity / coalign / roco / roco_antialias behind the
``reject_margin`` guard) and ``learned_fallback`` (select over [roco_antialias,
roco_fallback] behind the ``keep_tested`` guard with ``prefer``, below); any other file
is ``learned_select:weights=PATH``.

A select-mode file may hold a ``guard`` in its metadata (:class:`Guard`), which reads
choice ``k``'s significance statistic (``choice_diagnostics[slot, k, statistic] == -1``:
the choice found nothing to test the collaborator's pose by, whether or not it moved it;
such a slot is "untested"):

* ``{"keep": k, "reject_margin": m}``: the policy takes choice ``k`` for every tested slot
  and rejects an untested one when the reject logit is at least choice ``k``'s minus
  ``m``. The network decides only where the aligner is blind; it cannot switch aligners or
  reject a slot the aligner tested.
* ``{"keep": k, "untested": "reject", "tested": "network"}`` (``train-policy --guard
  reject_untested``): every untested slot is rejected by rule, and the network's argmax
  decides every tested slot (any choice or reject). Training applied the same rule to the
  sampled actions, so the network learned only the decisions the rule leaves open.
* ``{"keep": k, "tested": "keep", "untested": "network"}`` (``train-policy --guard
  keep_tested``): every tested slot takes choice ``k``, and the network's argmax decides
  every untested slot (any choice or reject): where ``k`` could not test a pose, another
  choice (e.g. roco_fallback's prior-free recovery) may. With ``"prefer": p`` (and
  ``"prefer_within_m": m``; ``train-policy --guard-prefer``, two choices) a tested slot
  takes choice ``p`` instead where its pose lies within ``m`` metres of choice ``k``'s
  (``choice_diagnostics`` column ``gap_m``; no ``m``: always): the tested slots follow
  the fixed rule ``reject_untested:tested=...,tested_within_m=m`` (hand rule C over
  [roco_antialias, roco_fallback]) and the network decides only the untested ones.

Because it acts in the env modes it was trained in, it declares them in
:attr:`LearnedPolicy.env_overrides`; sweeps (``roco-env compare``/``run``) and
:class:`roco_env.wrappers.EgoEnv` merge them into the env they build (docs/learning.md).
torch is imported when a policy is built, not with this module.
"""

from __future__ import annotations

import json
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from roco_env.policies.base import StatelessPolicy
from roco_env.policies.reject_untested import (
    GAP_CLIP_M,
    STATISTIC,
    tested_choice,
    untested_slots,
)
from roco_env.schema import build, spec

FORMAT = "roco_env.learned_policy/1"
WEIGHTS_DIR = Path(__file__).resolve().parent / "weights"
# registered name -> (shipped weights file, the action mode that name acts in)
SHIPPED = {"learned_select": ("learned_select.pt", "select"),
           "learned_fallback": ("learned_fallback.pt", "select")}
_REQUIRED_META = ("format", "env_overrides", "observation", "action")


@dataclass(frozen=True)
class Guard:
    """Where a select-mode network may deviate (module docstring): ``keep``, the index of
    the choice whose statistic says which slots are untested; ``reject_margin``, how far
    (in logits) the reject logit may fall below choice ``keep``'s on an untested slot and
    still win, or None: every untested slot is rejected; ``tested``, who decides a tested
    slot: ``"keep"`` (choice ``keep``) or ``"network"`` (the network's argmax);
    ``untested``, who decides an untested slot: ``"rule"`` (``reject_margin``) or
    ``"network"`` (the network's argmax, ``reject_margin`` None); ``prefer`` (with
    ``tested`` ``"keep"``): the index of the choice a tested slot takes instead of
    ``keep`` where its ``gap_m`` is at most ``prefer_within_m`` m (None: always), or
    None."""

    keep: int
    reject_margin: float | None
    tested: str = "keep"
    untested: str = "rule"
    prefer: int | None = None
    prefer_within_m: float | None = None

    def act(self, logits: np.ndarray, choice_diagnostics: np.ndarray,
            collab_mask: np.ndarray) -> np.ndarray:
        """(N,) int64 actions from (N, C + 1) logits (last: reject) and the (N, C, ...)
        choice diagnostics of the observation."""
        reject = logits.shape[1] - 1
        blind = self.untested_slots(choice_diagnostics, collab_mask)
        if self.untested == "network":
            on_blind = np.argmax(logits, axis=1)
        elif self.reject_margin is None:
            on_blind = np.full(len(blind), reject)
        else:
            wants = logits[:, reject] >= logits[:, self.keep] - self.reject_margin
            on_blind = np.where(wants, reject, self.keep)
        on_tested = np.argmax(logits, axis=1) if self.tested == "network" else \
            self.tested_choice(choice_diagnostics)
        return np.where(blind, on_blind, on_tested).astype(np.int64)

    def constrain(self, action: np.ndarray, reject: int, choice_diagnostics: np.ndarray,
                  collab_mask: np.ndarray) -> np.ndarray:
        """(N,) int64: a sampled ``action`` (N,) with the guard's rules applied (training
        plays them so): untested slots rejected (index ``reject``) unless the network
        decides them, tested ones given choice ``keep`` unless the network decides them."""
        blind = self.untested_slots(choice_diagnostics, collab_mask)
        on_blind = action if self.untested == "network" else reject
        on_tested = action if self.tested == "network" else \
            self.tested_choice(choice_diagnostics)
        return np.where(blind, on_blind, on_tested).astype(np.int64)

    def rule(self, reject: int, choice_diagnostics: np.ndarray,
             collab_mask: np.ndarray) -> np.ndarray:
        """(N,) int64: the guard's fixed rule alone, the reference a network behind it has
        to beat: every untested slot rejected (index ``reject``), every tested one given
        :meth:`tested_choice` (``keep`` where the network decides them)."""
        blind = self.untested_slots(choice_diagnostics, collab_mask)
        return np.where(blind, reject, self.tested_choice(choice_diagnostics)).astype(np.int64)

    def tested_choice(self, choice_diagnostics: np.ndarray) -> np.ndarray:
        """(N,) int64: the choice the rule gives each slot it treats as tested: ``keep``,
        or ``prefer`` where its ``gap_m`` is at most ``prefer_within_m`` (or always)."""
        return tested_choice(choice_diagnostics, self.keep, self.prefer, self.prefer_within_m)

    def untested_slots(self, choice_diagnostics: np.ndarray,
                       collab_mask: np.ndarray) -> np.ndarray:
        """(N,) bool: the filled slots choice ``keep`` computed no statistic for."""
        # "statistic" has one index in DIAGNOSTICS and CHOICE_DIAGNOSTICS (tested)
        return untested_slots(np.asarray(choice_diagnostics)[:, self.keep, STATISTIC],
                              collab_mask)


def rule_guard(keep: int) -> dict:
    """The metadata of the guard that rejects every slot choice ``keep`` left untested and
    lets the network decide the tested ones (``train-policy --guard reject_untested``)."""
    return {"keep": keep, "untested": "reject", "tested": "network"}


def keep_tested_guard(keep: int, prefer: int | None = None,
                      prefer_within_m: float | None = None) -> dict:
    """The metadata of the guard that gives every slot choice ``keep`` tested that choice
    (or ``prefer`` within ``prefer_within_m`` m of it, :class:`Guard`) and lets the network
    decide the untested ones (``train-policy --guard keep_tested [--guard-prefer ...]``)."""
    guard: dict = {"keep": keep, "tested": "keep", "untested": "network"}
    if prefer is not None:
        guard["prefer"] = prefer
        if prefer_within_m is not None:
            guard["prefer_within_m"] = prefer_within_m
    return guard


def guard_metadata(guard: Guard) -> dict:
    """The metadata of a training guard (:func:`rule_guard` or :func:`keep_tested_guard`)."""
    if guard.untested == "network":
        return keep_tested_guard(guard.keep, guard.prefer, guard.prefer_within_m)
    return rule_guard(guard.keep)


def load_weights(path: str | Path) -> tuple[dict, dict]:
    """(state_dict, metadata) of a learned-policy weights file, checked.

    Never unpickles: ``torch.load(weights_only=True)``. Raises ValueError naming the file
    for a missing or unreadable file, a wrong layout or format, and for NaN/inf tensors.
    """
    import torch

    path = Path(path)
    if not path.is_file():
        raise ValueError(f"learned policy weights file {path} does not exist")
    try:
        raw = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as exc:  # noqa: BLE001 - any unreadable file is the same user error
        raise ValueError(f"learned policy weights file {path} cannot be read as a "
                         f"weights-only torch file: {exc}") from exc
    if not isinstance(raw, dict) or not isinstance(raw.get("state_dict"), dict) \
            or not isinstance(raw.get("metadata"), str):
        raise ValueError(f"learned policy weights file {path} must hold a dict with "
                         "'state_dict' (tensors) and 'metadata' (JSON text)")
    try:
        metadata = json.loads(raw["metadata"])
    except json.JSONDecodeError as exc:
        raise ValueError(f"learned policy weights file {path}: metadata is not JSON: "
                         f"{exc}") from exc
    missing = [key for key in _REQUIRED_META if key not in metadata]
    if missing:
        raise ValueError(f"learned policy weights file {path}: metadata lacks {missing}")
    if metadata["format"] != FORMAT:
        raise ValueError(f"learned policy weights file {path}: format "
                         f"{metadata['format']!r}; this version reads {FORMAT!r}")
    state = raw["state_dict"]
    bad = sorted(name for name, value in state.items()
                 if not isinstance(value, torch.Tensor) or not bool(torch.isfinite(value).all()))
    if bad:
        raise ValueError(f"learned policy weights file {path} holds non-finite (NaN or inf) "
                         f"or non-tensor values in {bad}")
    return state, metadata


class LearnedPolicy(StatelessPolicy):
    """A trained MLP acting in the env modes its weights file names (see module docstring).

    weights: the weights file (default: the shipped file of ``name``); name: the
    registered name (errors and labels); action_mode: the mode this name acts in, or
    None to take the file's; reject_margin: replaces the file's guard margin (None: the
    file's). Raises ValueError naming the file and the field when the file was trained for
    another action mode, or its guard is malformed or missing where a margin is given.
    """

    def __init__(self, weights: str | None = None, *, name: str = "learned",
                 action_mode: str | None = None, reject_margin: float | None = None) -> None:
        import torch

        if weights is not None and not isinstance(weights, str):
            raise ValueError(f"policy {name!r}: weights must be a file path; got {weights!r}")
        self.name = name
        self.path = Path(weights) if weights else WEIGHTS_DIR / SHIPPED[name][0]
        state, self.metadata = load_weights(self.path)
        self.env_overrides: dict[str, Any] = dict(self.metadata["env_overrides"])
        mode = self.env_overrides.get("action.mode")
        if action_mode is not None and mode != action_mode:
            raise ValueError(f"learned policy weights file {self.path}: action.mode is "
                             f"{mode!r}; {name!r} acts in action.mode {action_mode!r}")
        self._keys = [(key, tuple(shape)) for key, shape in self.metadata["observation"]]
        size = sum(int(np.prod(shape)) for _, shape in self._keys)
        self._scale = state["input_scale"].double().numpy()
        if self._scale.shape != (size,) or np.any(self._scale <= 0):
            raise ValueError(f"learned policy weights file {self.path}: input_scale must be "
                             f"({size},) positive values for its observation keys")
        self._clip = float(self.metadata.get("input_clip", np.inf))
        self._net = _build_mlp(state, self.path, size)
        self._action = self.metadata["action"]
        self.guard = _guard(self.metadata, self.path, reject_margin)
        self._torch = torch

    def __call__(self, observation: Mapping[str, Any], info: Mapping | None = None) -> np.ndarray:
        flat = scaled_observation(observation, self._keys, self._scale, self._clip,
                                  self._hint())
        with self._torch.no_grad():
            out = self._net(self._torch.as_tensor(flat)[None])[0]
        out = out.double().numpy()
        if self.guard is not None:
            nvec = self._action["nvec"]
            return self.guard.act(out.reshape(len(nvec), nvec[0]),
                                  observation["choice_diagnostics"], observation["collab_mask"])
        if "nvec" in self._action:  # MultiDiscrete: argmax per slot
            splits = np.cumsum(self._action["nvec"])[:-1]
            return np.array([int(np.argmax(part)) for part in np.split(out, splits)],
                            dtype=np.int64)
        low, high = np.asarray(self._action["low"]), np.asarray(self._action["high"])
        return np.clip(out.reshape(self._action["shape"]), low, high).astype(np.float32)

    def input_files(self) -> list[Path]:
        """The weights file: sweeps hash it, so retrained weights make old results stale."""
        return [self.path]

    def _hint(self) -> str:
        choices = self.env_overrides.get("action.choices")
        if choices is None:  # files from before the choices were recorded
            from roco_env.scenario import ActionConfig  # lazy: the scenario layer is higher

            choices = f"the default ({', '.join(ActionConfig().choices)})"
        return (f"policy {self.name!r} ({self.path.name}) was trained with observation.mode="
                f"{self.env_overrides.get('observation.mode', 'raw')!r}, max_collaborators="
                f"{self.env_overrides.get('max_collaborators')}, max_boxes="
                f"{self.env_overrides.get('max_boxes')}, action.choices={choices}: build the "
                "env with the policy's env_overrides (sweeps and EgoEnv do)")


def _guard(metadata: dict, path: Path, reject_margin: float | None) -> Guard | None:
    """The file's :class:`Guard` (its margin replaced by ``reject_margin`` when given),
    checked against its action and observation; None for a file without one."""
    raw = metadata.get("guard")
    if raw is None:
        if reject_margin is not None:
            raise ValueError(f"learned policy weights file {path} has no guard; "
                             "reject_margin applies only to a file with one")
        return None
    keys = [key for key, _ in metadata["observation"]]
    nvec = metadata["action"].get("nvec", [])
    rule = isinstance(raw, dict) and raw == rule_guard(raw.get("keep"))
    keep_tested = isinstance(raw, dict) and raw == keep_tested_guard(
        raw.get("keep"), raw.get("prefer"), raw.get("prefer_within_m"))
    if not isinstance(raw, dict) or (set(raw) != {"keep", "reject_margin"} and not rule
                                     and not keep_tested) \
            or "choice_diagnostics" not in keys or "collab_mask" not in keys \
            or len(set(nvec)) != 1 or not isinstance(raw["keep"], int) \
            or not 0 <= raw["keep"] < nvec[0] - 1:
        raise ValueError(f"learned policy weights file {path}: guard must be "
                         "{'keep': a choice index, 'reject_margin': logits} or "
                         "{'keep': a choice index, 'untested': 'reject', 'tested': "
                         "'network'} or {'keep': a choice index, 'tested': 'keep', "
                         "'untested': 'network'[, 'prefer': a choice index[, "
                         "'prefer_within_m': m]]} on a select policy that reads "
                         "choice_diagnostics and "
                         f"collab_mask; got {raw!r}")
    if rule or keep_tested:
        if reject_margin is not None:
            what = "rejects" if rule else "lets the network decide"
            raise ValueError(f"learned policy weights file {path}: its guard {what} every "
                             "untested slot; reject_margin applies only to a guard with one")
        if rule:
            return Guard(raw["keep"], None, "network")
        return Guard(raw["keep"], None, "keep", "network", *_prefer(raw, nvec[0] - 1, path))
    margin = raw["reject_margin"] if reject_margin is None else reject_margin
    if not isinstance(margin, int | float) or isinstance(margin, bool) \
            or not np.isfinite(margin):
        raise ValueError(f"learned policy weights file {path}: reject_margin must be a "
                         f"finite number of logits; got {margin!r}")
    return Guard(raw["keep"], float(margin))


def _prefer(raw: dict, choices: int, path: Path) -> tuple[int | None, float | None]:
    """(prefer, prefer_within_m) of a keep_tested guard's metadata ``raw``, checked: a
    choice index other than ``keep`` among two ``choices``, and m in [0, 20) or absent."""
    prefer, within = raw.get("prefer"), raw.get("prefer_within_m")
    if prefer is None:
        return None, None
    if not isinstance(prefer, int) or isinstance(prefer, bool) or choices != 2 \
            or not 0 <= prefer < choices or prefer == raw["keep"]:
        raise ValueError(f"learned policy weights file {path}: guard prefer must be the "
                         f"index of the other of two choices (keep is {raw['keep']}, "
                         f"choices {choices}); got {prefer!r}")
    if within is not None and (not isinstance(within, int | float) or isinstance(within, bool)
                               or not 0 <= within < GAP_CLIP_M):
        raise ValueError(f"learned policy weights file {path}: guard prefer_within_m must "
                         f"be m in [0, {GAP_CLIP_M:g}) or absent; got {within!r}")
    return prefer, None if within is None else float(within)


def scaled_observation(observation: Mapping[str, Any], keys: list[tuple[str, tuple]],
                       scale: np.ndarray, clip: float, hint: str = "") -> np.ndarray:
    """What the network reads: the flat observation / ``scale``, clipped to +-``clip``,
    float32 (training and :class:`LearnedPolicy` share this function)."""
    flat = flatten_observation(observation, keys, hint) / scale
    return np.clip(flat, -clip, clip).astype(np.float32)


def flatten_observation(observation: Mapping[str, Any], keys: list[tuple[str, tuple]],
                        hint: str = "") -> np.ndarray:
    """The observation's ``keys`` raveled and concatenated in order (float64), each checked
    against its shape; a missing key or another shape is a ValueError naming it (+ hint)."""
    parts = []
    for key, shape in keys:
        if not isinstance(observation, Mapping) or key not in observation:
            raise ValueError(f"the observation has no {key!r} entry; {hint}")
        value = np.asarray(observation[key], dtype=np.float64)
        if value.shape != tuple(shape):
            raise ValueError(f"observation[{key!r}] has shape {value.shape}, expected "
                             f"{tuple(shape)}; {hint}")
        parts.append(value.reshape(-1))
    return np.concatenate(parts)


def _build_mlp(state: dict, path: Path, size: int):
    """``torch.nn.Sequential`` of the state dict's ``layers.<i>`` linears with tanh between."""
    import torch

    count = 0
    while f"layers.{count}.weight" in state:
        count += 1
    if count == 0:
        raise ValueError(f"learned policy weights file {path}: no 'layers.0.weight'")
    modules: list = []
    width = size
    for index in range(count):
        weight, bias = state[f"layers.{index}.weight"], state.get(f"layers.{index}.bias")
        if weight.ndim != 2 or weight.shape[1] != width or bias is None \
                or bias.shape != (weight.shape[0],):
            raise ValueError(f"learned policy weights file {path}: layers.{index} has weight "
                             f"{tuple(weight.shape)}, expected (*, {width}) with a matching bias")
        linear = torch.nn.Linear(width, weight.shape[0])
        linear.weight.data.copy_(weight.float())
        linear.bias.data.copy_(bias.float())
        modules += [linear, torch.nn.Tanh()]
        width = weight.shape[0]
    return torch.nn.Sequential(*modules[:-1]).eval()


@dataclass(frozen=True)
class LearnedSelectParams:
    """The parameters of the shipped select policies ``learned_select`` and
    ``learned_fallback`` (:data:`SHIPPED`)."""

    weights: str | None = spec(None, doc="weights file (None: the shipped one)")
    reject_margin: float | None = spec(None, doc="logits by which the reject logit may "
                                       "trail the kept choice's on a slot it could not "
                                       "test (None: the file's guard; only for a file "
                                       "with a guard)")


def learned_select(**params: Any) -> LearnedPolicy:
    """The shipped select-mode policy over identity / coalign / roco / roco_antialias
    (``roco-env train-policy``; docs/learning.md); params: the fields of
    :class:`LearnedSelectParams`."""
    return _shipped_select("learned_select", params)


def learned_fallback(**params: Any) -> LearnedPolicy:
    """The shipped select-mode policy over [roco_antialias, roco_fallback]: hand rule C
    (``reject_untested:tested=roco_fallback,tested_within_m=0.5``) on the slots
    roco_antialias tested, a PPO-trained network on the untested ones (roco_antialias,
    roco_fallback or reject; docs/learning.md); params: the fields of
    :class:`LearnedSelectParams` (its guard has no reject_margin)."""
    return _shipped_select("learned_fallback", params)


def _shipped_select(name: str, params: dict[str, Any]) -> LearnedPolicy:
    built = build(LearnedSelectParams, params, name)
    return LearnedPolicy(built.weights, name=name, action_mode="select",
                         reject_margin=built.reject_margin)

