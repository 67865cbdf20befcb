"""The ceiling of detecting ghosts, erased objects and the consistent spoof on the attack
protocol's own episodes (docs/attacks.md; the small spoof's ceiling: spoof_ceiling.py).

    python baselines/attack_protocol/evidence_ceiling.py                   # the protocol's
    python baselines/attack_protocol/evidence_ceiling.py --attacks "ghosts 5" --seeds 2

The best any detector can do on one ego's evidence. It is told everything the attacker did
(privileged: which boxes are ghosts, which objects were erased, the spoof's offset) and
sees every honest source's pose exactly (perfect alignment); what it lacks is whether the
evidence a message allows could have come from an honest collaborator. It plays the
protocol's episodes (the scenes, seeds, steps, noise 0.4, the realistic detector; its
frames do not depend on any policy) and, per honest ego and step with the attacker among
its collaborators, collects that evidence from the ego's own view and its honest
collaborators' messages (the witnesses):

* **ghost** (a box with object id -1 and the ghosts' score, in the attacker's true frame):
  evidence where an honest witness would have detected a real car there and has not.
  Every ghost is put into the world as a car at once (under "honest" all of them would be
  real), the visibility model casts its rays, and the detector's probability of detecting
  it (``detection_probability`` of its LiDAR returns) is ``r``: honest, the witness misses
  it with probability ``1 - r``; a ghost it misses surely. A ghost whose centre lies within
  ``--near-m`` of a real object looks like that object to everyone: no evidence.
* **erase**: an object the attacker detected and did not send, that an honest witness
  detected (so the defender knows it is there): honest, the attacker misses it with
  probability ``1 - r``, ``r`` its own detection probability of that object.
* **consistent spoof**: the attacker's real car detected by an honest witness, or an
  object of its message that is not forged (the victim does not detect it) detected by an
  honest collaborator: either places the attacker's boxes ``offset_m`` away from the
  truth, a Gaussian measurement of the known offset with the relative noise of two agents'
  reported poses (spoof_ceiling's ``relative_sigma``; one measurement per step, as the
  step's pose noise is shared by its boxes). Where no witness detects the real car, the
  claimed place (the attacker's car moved by the offset) gives ghost-like evidence: a
  witness that would have detected a car there (``r``) and has none.

All evidence is taken as independent (over witnesses and steps) and a ghost's or claim's
miss as certain under the attack: both favour the detector, so this is an upper bound.
Per (ego, step) the evidence so far is a probability ``P0`` that an honest collaborator
shows every miss, and a Gaussian strength ``S`` (offset / sigma x sqrt(steps with a
measurement)). Under the attack the misses are certain, so the most powerful test at
false-alarm rate ``alpha`` (Neyman-Pearson) rejects only when every miss is there, and then
at level ``alpha / P0`` on the Gaussian part: it detects with probability
``Phi(S - Phi^-1(1 - min(1, alpha / P0)))`` (``min(1, alpha / P0)`` without a measurement).
The share of (ego, step) detected is that mean over the protocol; ``pooled_power`` is the
ceiling of a detector bound only by its mean false-alarm rate over all of them (spending
it where the evidence is strongest).
"""

from __future__ import annotations

import argparse
import dataclasses
import importlib.util
import sys
from collections.abc import Sequence
from pathlib import Path
from typing import NamedTuple

import numpy as np
from scipy.stats import norm

from roco_env.attacks.pose import offset_pose
from roco_env.geometry import se2_compose, se2_inverse, transform_boxes
from roco_env.sensing.visibility import compute_visibility
from roco_env.sweeps.attack_protocol import ATTACKS, NOISE, PROTOCOL, SCENES
from roco_env.sweeps.cells import build_grid
from roco_env.sweeps.episode import make_env
from roco_env.traffic.state import WorldState

_SPEC = importlib.util.spec_from_file_location(
    "spoof_ceiling", Path(__file__).with_name("spoof_ceiling.py"))
spoof_ceiling = importlib.util.module_from_spec(_SPEC)
_SPEC.loader.exec_module(spoof_ceiling)

# the protocol's attacks whose evidence this script knows: ghosts, erase, the consistent spoof
KNOWN = tuple(label for label, attack in ATTACKS.items()
              if attack.get("attack.kind") in ("ghost", "erase")
              or (attack.get("attack.kind") == "pose_spoof"
                  and attack.get("attack.params.consistent") is True))
DEFAULT_ATTACKS = ("ghosts 5", "erase 50%", "spoof 3 m consistent")


class StepEvidence(NamedTuple):
    """One honest ego's evidence against the attacker at one step: ``misses`` (k,) the
    probabilities ``r`` with which an honest collaborator's evidence would have been seen
    (each missed here), ``measured`` whether a Gaussian measurement of the offset exists."""

    misses: np.ndarray
    measured: bool = False


def np_power(strength: np.ndarray, p0: np.ndarray, alpha: np.ndarray | float) -> np.ndarray:
    """The most powerful test's detection probability at false-alarm rate ``alpha``, where
    the attack shows misses an honest collaborator shows with probability ``p0`` (and the
    attack certainly) and a Gaussian shift ``strength`` (offset / std; 0: no measurement)."""
    strength, p0 = np.asarray(strength, dtype=float), np.asarray(p0, dtype=float)
    level = np.minimum(1.0, np.asarray(alpha, dtype=float) / np.maximum(p0, 1e-300))
    with np.errstate(divide="ignore"):
        return np.where(level >= 1.0, 1.0, norm.cdf(strength - norm.isf(level)))


def pooled_power(strength: np.ndarray, p0: np.ndarray, alpha: float) -> float:
    """The largest mean of :func:`np_power` over the items (strength, p0 (n,) each) whose
    per-item false-alarm rates average ``alpha``: each item's power is concave in its
    rate, so a Lagrange multiplier (bisected) spends the rates where they gain most."""
    strength, p0 = np.asarray(strength, dtype=float), np.asarray(p0, dtype=float)
    # candidate rates per item: a log grid, and p0 itself (where a test without a
    # measurement reaches power 1)
    rates = np.concatenate([np.broadcast_to(np.concatenate([[0.0], np.logspace(-12, 0, 481)]),
                                            (p0.shape[0], 482)), np.minimum(p0, 1.0)[:, None]],
                           axis=1)
    power = np_power(strength[:, None], p0[:, None], rates)

    def spend(log_price: float) -> np.ndarray:
        """Each item's best rate's row index at the price ``exp(log_price)`` per rate."""
        return np.argmax(power - np.exp(log_price) * rates, axis=1)

    rows = np.arange(p0.shape[0])
    low, high = np.log(1e-6), np.log(1e14)  # all rates 1 .. all rates 0
    for _ in range(100):
        middle = 0.5 * (low + high)
        low, high = (middle, high) if rates[rows, spend(middle)].mean() > alpha \
            else (low, middle)
    return float(power[rows, spend(high)].mean())


def _recall(detector, visibility, agents: np.ndarray, objects: np.ndarray) -> np.ndarray:
    """(len(agents), len(objects)) each agent's probability of detecting each object (the
    detector's model: visible with enough of it, then its LiDAR returns)."""
    fraction = visibility.fraction[np.ix_(agents, objects)]
    seen = visibility.visible[np.ix_(agents, objects)] & (
        fraction > detector.params["min_fraction"])
    return np.where(seen, detector.detection_probability(
        visibility.returns[np.ix_(agents, objects)]), 0.0)


def _with_cars(state: WorldState, boxes: np.ndarray) -> WorldState:
    """``state`` with car boxes (G, 7, world) added as objects (new ids, at rest)."""
    count = boxes.shape[0]
    first = int(state.object_ids.max(initial=0)) + 1
    return dataclasses.replace(
        state, object_ids=np.concatenate([state.object_ids, first + np.arange(count)]),
        object_classes=np.concatenate([state.object_classes,
                                       np.zeros(count, dtype=state.object_classes.dtype)]),
        object_boxes=np.concatenate([state.object_boxes.reshape(-1, 7), boxes]),
        object_velocities=np.concatenate([state.object_velocities.reshape(-1, 2),
                                          np.zeros((count, 2))]))


def _unseen_places(env, frame, witnesses: list[int], boxes: np.ndarray,
                   near_m: float) -> np.ndarray:
    """The probabilities ``r`` (k,) of the (place, witness) pairs where a real car at a
    place (world boxes (G, 7)) would have been detected by the witness, for the places
    farther than ``near_m`` from every real object. A witness's false positive that happens
    to lie at a place is not looked for (the place counts as missed): one more way in which
    the ceiling is generous."""
    if boxes.shape[0] == 0:
        return np.zeros(0)
    real = frame.state.object_boxes.reshape(-1, 7)[:, :2]
    gap = np.hypot(*(boxes[:, None, :2] - real[None, :, :2]).transpose(2, 0, 1))
    free = gap.min(axis=1, initial=np.inf) > near_m
    state = _with_cars(frame.state, boxes)
    visibility = compute_visibility(state)
    count = frame.state.object_boxes.reshape(-1, 7).shape[0]
    recall = _recall(env.pipeline.detector, visibility, np.asarray(witnesses),
                     count + np.arange(boxes.shape[0]))
    return recall[free[None, :] & (recall > 0.0)]


def step_evidence(env, frame, victim: int, slot: int, attacker: int, near_m: float
                  ) -> StepEvidence:
    """The evidence ``victim`` has against ``attacker`` (its collaborator in ``slot``) in
    ``frame`` (privileged; module docstring)."""
    view = frame.views[victim]
    attackers = set(env.pipeline.attack.attackers)
    witnesses = [victim] + [c for c in view.collaborators if c not in attackers]
    ids = {victim: set(frame.detections[victim].object_ids.tolist())}
    for k, sender in enumerate(view.collaborators):
        if sender not in attackers:
            ids[sender] = set(view.collab_object_ids[k].tolist())
    known = set().union(*ids.values()) - {-1}
    sent = np.asarray(view.collab_object_ids[slot])
    attack = env.pipeline.attack
    kind = env.config.attack.kind
    true_pose = frame.state.agent_poses[attacker]
    if kind == "ghost":
        rows = (sent == -1) & (np.asarray(view.collab_scores[slot]) >= attack.params.score)
        ghosts = transform_boxes(np.asarray(view.collab_boxes[slot])[rows], true_pose)
        return StepEvidence(_unseen_places(env, frame, witnesses, ghosts, near_m))
    if kind == "erase":
        detected = frame.detections[attacker].object_ids
        erased = [o for o in detected.tolist() if o >= 0 and o not in set(sent.tolist())
                  and o in known]
        index = {o: k for k, o in enumerate(frame.state.object_ids.tolist())}
        recall = _recall(env.pipeline.detector, frame.visibility, np.array([attacker]),
                         np.array([index[o] for o in erased], dtype=np.int64))[0]
        return StepEvidence(recall[recall > 0.0])
    if kind != "pose_spoof" or not attack.params.consistent:
        raise ValueError(f"evidence_ceiling: attack.kind {kind!r} (consistent="
                         f"{getattr(attack.params, 'consistent', None)}) is not one of the "
                         f"attacks it knows: ghost, erase, pose_spoof with consistent")
    car = int(frame.state.agent_object_ids[attacker])
    unforged = {o for o in sent.tolist()
                if o >= 0 and o not in set(frame.detections[victim].object_ids.tolist())}
    measured = any(car in ids[w] for w in witnesses) or any(
        unforged & ids[w] for w in witnesses if w != victim)
    if measured:
        return StepEvidence(np.zeros(0), True)
    p = attack.params
    claim = se2_compose(true_pose, offset_pose(p.offset_m, p.direction_deg, p.offset_deg))
    moved = se2_compose(claim, se2_inverse(true_pose))  # the car's box to the claimed place
    index = list(frame.state.object_ids).index(car)
    box = transform_boxes(frame.state.object_boxes.reshape(-1, 7)[index:index + 1], moved)
    return StepEvidence(_unseen_places(env, frame, witnesses, box, near_m))


def attack_items(scene: str, label: str, seeds: Sequence[int], steps: int, sigma: float,
                 offset_m: float, near_m: float) -> tuple[np.ndarray, np.ndarray]:
    """(strength, p0) (n,) per (seed, honest ego, step) with the attacker among the ego's
    collaborators, the evidence accumulated over the episode's steps so far."""
    strength, p0 = [], []
    for seed in seeds:
        (cell,) = build_grid([scene], [NOISE], ["roco"], [seed], steps,
                             overrides={**PROTOCOL, **SCENES[scene], **ATTACKS[label]})
        env = make_env(cell)
        try:
            env.reset(seed=seed)
            frame = env._frame  # the reset frame; the pipeline advances the rest
            totals: dict[int, tuple[int, float]] = {}
            for step in range(steps):
                if step:
                    frame = env.pipeline.advance()
                attackers = env.pipeline.attack.attackers
                for victim, view in enumerate(frame.views):
                    if victim in attackers:
                        continue
                    for slot, sender in enumerate(view.collaborators):
                        if sender not in attackers:
                            continue
                        seen = step_evidence(env, frame, victim, slot, sender, near_m)
                        count, log_p0 = totals.get(victim, (0, 0.0))
                        count += int(seen.measured)
                        log_p0 += float(np.sum(np.log1p(-np.minimum(seen.misses, 1.0 - 1e-12))))
                        totals[victim] = (count, log_p0)
                        strength.append(offset_m / sigma * np.sqrt(count))
                        p0.append(np.exp(log_p0))
        finally:
            env.close()
    return np.array(strength), np.array(p0)


def _check(args: argparse.Namespace) -> None:
    unknown = [label for label in args.attacks if label not in KNOWN]
    if unknown:
        raise ValueError(f"--attacks: {unknown} not known here; choose among {list(KNOWN)}")
    bad = [scene for scene in args.scenes if scene not in SCENES]
    if bad:
        raise ValueError(f"--scenes: {bad} not in the protocol; choose among {list(SCENES)}")
    if not 0.0 < args.alpha < 1.0:
        raise ValueError(f"--alpha must lie in (0, 1); got {args.alpha}")
    if args.seeds < 1 or args.steps < 1:
        raise ValueError(f"--seeds and --steps must be >= 1; got {args.seeds}, {args.steps}")
    if not args.near_m >= 0.0:
        raise ValueError(f"--near-m must be >= 0; got {args.near_m}")


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--attacks", nargs="+", default=list(DEFAULT_ATTACKS))
    parser.add_argument("--scenes", nargs="+", default=list(SCENES))
    parser.add_argument("--seeds", type=int, default=2, help="seeds 0..n-1 (the protocol's: 2)")
    parser.add_argument("--steps", type=int, default=10)
    parser.add_argument("--alpha", type=float, default=0.02, help="false alarms per step")
    parser.add_argument("--near-m", type=float, default=2.0,
                        help="a ghost this near a real object looks like it, m")
    args = parser.parse_args(argv)
    try:
        _check(args)
    except ValueError as exc:
        parser.error(str(exc))
    sigma = spoof_ceiling.relative_sigma(NOISE, NOISE, 0.0)
    print(f"alpha {args.alpha:g} per step, seeds 0..{args.seeds - 1}, {args.steps} steps; "
          f"detected share of (honest ego, step) with the attacker a collaborator")
    print("scene | attack | items | with evidence | flat alpha | alpha pooled over the protocol")
    for scene in args.scenes:
        for label in args.attacks:
            offset = float(ATTACKS[label].get("attack.params.offset_m", 0.0))
            strength, p0 = attack_items(scene, label, range(args.seeds), args.steps, sigma,
                                        offset, args.near_m)
            flat = np_power(strength, p0, args.alpha).mean()
            pooled = pooled_power(strength, p0, args.alpha)
            some = np.mean((strength > 0) | (p0 < 1.0))
            print(f"{scene} | {label} | {strength.shape[0]} | {100 * some:.1f} % | "
                  f"{100 * flat:.1f} % | {100 * pooled:.1f} %")
    return 0


if __name__ == "__main__":
    sys.exit(main())
