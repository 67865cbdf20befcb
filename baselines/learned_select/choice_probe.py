"""Can the observation tell where to deviate from hand rule C? (privileged probe, not shipped)

    nice -n 10 python baselines/learned_select/choice_probe.py --out runs/near_probe \
        [--target near] [--probe logistic [mlp]] [--features obs [slot obs+slot]] [--tuned] \
        [--scenarios parking_lot] [--noise 1.5 3.0] [--train-seeds 6] [--seeds 3]

Hand rule C (``headroom_c.py``) gives a tested slot roco_fallback's pose where it lies
within 0.5 m of roco_antialias's ("near" slots), else roco_antialias's, and rejects the
untested slots. ``headroom_c.py``'s privileged variants gain over C by deviating with the
truth; this probe asks whether a policy could learn such a deviation from what it
observes. Per ``--target``:

* ``near``: on each near slot, roco_antialias's pose instead of roco_fallback's; label 1
  where roco_antialias's pose is the closer to the truth (``tested_near_best``'s choice);
* ``reject``: on each tested slot, reject; label 1 where rejecting that slot alone raises
  the agent's AP@0.7 on that frame (the privileged per-frame AP the AP-aware variants of
  ``headroom_c.py`` maximise).

A probe on each such slot's observation row (``choice_diagnostics`` of both choices, then
``diagnostics``: what a select-mode network behind C's guard reads for that slot) is
fitted to the label on env seeds 1,000,000 and up (the training range): a supervised
signal stronger than any reward. ``--probe logistic`` (default): an L2 logistic
regression on the standardised inputs; ``mlp``: a tanh MLP of train-policy's default
widths (64, 64), its epoch chosen on the last training seed (early stopping). On the
held-out seeds 0 .. ``--seeds`` - 1 it plays C and scores, on the same frames
(``headroom_c.play_c``): ``headroom_c_c`` (C), ``probe_<target>`` (C, deviating on the
slots the probe gives p >= 0.5; ``probe_<target>_mlp`` for the MLP) and
``truth_<target>`` (C, deviating on every slot whose label is 1).

``--features``: one probe per input set: ``obs`` (the observation row above), ``slot``
(``slot_features.py``: the slot's boxes against the ego's under C's pose, and what late
fusion of C's kept slots makes of them; no truth) or ``obs+slot`` (both); the columns of
the latter two add ``_slot`` / ``_obs_slot`` to the probe's name. ``--tuned``: each probe is
also played (``..._tuned``) at the threshold of :func:`tuned_threshold` on the last
training seed's slots (the deviation's summed per-frame gain; never a held-out seed).
Writes ``results.jsonl`` (``table.py``) and prints each probe's held-out AUC and how many
slots it deviates on, and per input set the single input column of the best held-out
AUC (and each slot feature's), with the slot and label counts.
"""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path

import numpy as np
from env_hook import record_cell
from headroom_c import PAIR, RULE_C, WITHIN_M, CFrame, play_c
from privileged_bound import grid_parser
from slot_features import NAMES, slot_features

from roco_env.metrics import APAccumulator
from roco_env.sweeps.cells import build_grid
from roco_env.training.rl.curriculum import TRAIN_SEED_BASE

TARGETS = ("near", "reject")
FEATURE_SETS = ("obs", "slot", "obs+slot")  # --features: the probe's input columns
L2 = 1.0  # the logistic regression's penalty on the weights (standardised inputs)
ITERATIONS, STEP = 3000, 0.5  # its full-batch gradient descent
EPOCHS, CHECK_EVERY = 1000, 25  # the MLP's full-batch Adam epochs, early-stopping checks
Probe = Callable[[np.ndarray], np.ndarray]  # (N, D) inputs -> (N,) probability of label 1


def probe_rows(frame: CFrame, target: str, with_slot: bool = False
               ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, int]:
    """(slots (k,), inputs (k, D), labels (k,) bool, gains (k,), the deviation's select
    index) of ``frame``'s slots ``target`` may deviate on (module docstring): each slot's
    observation row (then, ``with_slot``, its :func:`slot_features.slot_features` under
    C's action), its label, and what deviating on that slot alone gains (``reject``: the
    frame's AP@0.7; ``near``: m / deg of pose error; label = gain > 0)."""
    tested = ~frame.untested
    if target == "near":
        slots = np.flatnonzero(tested & (frame.gap <= WITHIN_M))
        gains, deviation = frame.errors[1, slots] - frame.errors[0, slots], 0
    else:
        slots, deviation = np.flatnonzero(tested), len(frame.errors)
        trials = np.repeat(frame.rule[None], len(slots) + 1, axis=0)
        trials[1 + np.arange(len(slots)), slots] = deviation
        ap = np.nan_to_num(frame.frame_ap(trials), nan=-1.0)
        gains = ap[1:] - ap[0]
    observation = frame.observation
    pair = observation["choice_diagnostics"][slots, :2]
    blocks = [pair.reshape(len(slots), 2 * pair.shape[2]), observation["diagnostics"][slots]]
    if with_slot:
        kept = frame.rule < len(frame.errors)
        poses = frame.poses[np.minimum(frame.rule, len(frame.errors) - 1),
                            np.arange(len(frame.rule))]
        blocks.append(slot_features(observation, poses, kept, slots))
    return (slots, np.concatenate(blocks, axis=1).astype(float), gains > 0, gains,
            deviation)


def fit_logistic(inputs: np.ndarray, labels: np.ndarray, held: np.ndarray) -> Probe:
    """An L2 logistic regression of ``labels`` (N,) on the standardised ``inputs`` (N, D)
    (full-batch gradient descent; ``held`` is not used: nothing to stop early)."""
    mean, scale = inputs.mean(axis=0), inputs.std(axis=0) + 1e-9

    def design(rows: np.ndarray) -> np.ndarray:
        return np.c_[(rows - mean) / scale, np.ones(len(rows))]

    weights = np.zeros(inputs.shape[1] + 1)
    for _ in range(ITERATIONS):
        probability = 1.0 / (1.0 + np.exp(-design(inputs) @ weights))
        weights -= STEP * (design(inputs).T @ (probability - labels) + L2 * weights) / len(labels)
    return lambda rows: 1.0 / (1.0 + np.exp(-design(rows) @ weights))


def fit_mlp(inputs: np.ndarray, labels: np.ndarray, held: np.ndarray) -> Probe:
    """A tanh MLP of train-policy's default widths (64, 64) on the standardised ``inputs``
    (N, D), fitted by Adam (full batch, seed 0) to ``labels`` (N,) on the samples not
    ``held`` (N,) bool; of up to :data:`EPOCHS` epochs, the one with the lowest log-loss
    on the held samples is kept (checked every :data:`CHECK_EVERY`)."""
    import torch

    threads = torch.get_num_threads()
    torch.set_num_threads(1)  # deterministic, and a small batch runs fastest so
    try:
        net, tensor = _train_mlp(inputs, labels, held)
    finally:
        torch.set_num_threads(threads)

    def probe(rows: np.ndarray) -> np.ndarray:
        with torch.no_grad():
            return torch.sigmoid(net(tensor(rows))[:, 0]).numpy().astype(float)
    return probe


def _train_mlp(inputs: np.ndarray, labels: np.ndarray, held: np.ndarray):
    """(net, tensor) of :func:`fit_mlp`: the trained network and the input scaling."""
    import torch

    torch.manual_seed(0)
    mean, scale = inputs.mean(axis=0), inputs.std(axis=0) + 1e-9

    def tensor(rows: np.ndarray):
        return torch.as_tensor((rows - mean) / scale, dtype=torch.float32)

    net = torch.nn.Sequential(torch.nn.Linear(inputs.shape[1], 64), torch.nn.Tanh(),
                              torch.nn.Linear(64, 64), torch.nn.Tanh(), torch.nn.Linear(64, 1))
    optimiser = torch.optim.Adam(net.parameters(), lr=1e-3)
    target = torch.as_tensor(labels, dtype=torch.float32)
    loss = torch.nn.functional.binary_cross_entropy_with_logits
    best = (float("inf"), [p.detach().clone() for p in net.parameters()])
    for epoch in range(1, EPOCHS + 1):
        optimiser.zero_grad()
        loss(net(tensor(inputs[~held]))[:, 0], target[~held]).backward()
        optimiser.step()
        if epoch % CHECK_EVERY == 0:
            with torch.no_grad():
                held_loss = float(loss(net(tensor(inputs[held]))[:, 0], target[held]))
            if held_loss < best[0]:
                best = (held_loss, [p.detach().clone() for p in net.parameters()])
    with torch.no_grad():
        for parameter, value in zip(net.parameters(), best[1], strict=True):
            parameter.copy_(value)
    return net, tensor


PROBES = {"logistic": fit_logistic, "mlp": fit_mlp}  # --probe: (inputs, labels, held) -> Probe


def auc(labels: np.ndarray, scores: np.ndarray) -> float:
    """Area under the ROC curve of ``scores`` (N,) for the bool ``labels`` (N,) (ties by
    order)."""
    ranks = np.empty(len(scores))
    ranks[np.argsort(scores, kind="stable")] = np.arange(len(scores))
    positives = int(labels.sum())
    negatives = len(labels) - positives
    return float((ranks[labels].sum() - positives * (positives - 1) / 2)
                 / (positives * negatives))


def feature_columns(feature_set: str, width: int, with_slot: bool) -> np.ndarray:
    """Column indices of ``feature_set`` (:data:`FEATURE_SETS`) in a probe row of ``width``
    columns (:func:`probe_rows`: ``with_slot``, it ends with the slot features)."""
    if feature_set not in FEATURE_SETS or (feature_set != "obs" and not with_slot):
        raise ValueError(f"feature_set must be one of {FEATURE_SETS} ('obs' only without "
                         f"slot features); got {feature_set!r}")
    first_slot = width - len(NAMES) if with_slot else width
    return {"obs": np.arange(first_slot), "slot": np.arange(first_slot, width),
            "obs+slot": np.arange(width)}[feature_set]


def tuned_threshold(probabilities: np.ndarray, gains: np.ndarray) -> float:
    """The threshold t of the highest total ``gains`` (N,) over the samples deviated on,
    those with ``probabilities`` (N,) >= t: one of the probabilities, or above them all
    (deviate nowhere, total 0); a tie takes the highest t (the most cautious)."""
    order = np.argsort(-probabilities, kind="stable")
    totals = np.concatenate([[0.0], np.cumsum(gains[order])])
    candidates = np.concatenate([[np.inf], probabilities[order]])
    # a threshold equal to a later probability also deviates on its ties: keep the last of each run
    last_of_run = np.r_[candidates[1:] != candidates[:-1], True]
    totals, candidates = totals[last_of_run], candidates[last_of_run]
    return float(candidates[np.flatnonzero(totals == totals.max())[0]])


def column_label(target: str, probe: str, feature_set: str, tuned: bool) -> str:
    """The results.jsonl policy of a probe: probe_<target>[_<probe>][_<features>][_tuned]
    (the logistic probe on the observation alone at 0.5 is plain ``probe_<target>``)."""
    return (f"probe_{target}" + ("" if probe == "logistic" else f"_{probe}")
            + ("" if feature_set == "obs" else "_" + feature_set.replace("+", "_"))
            + ("_tuned" if tuned else ""))


def main(argv: list[str] | None = None) -> None:
    parser = grid_parser(__doc__.splitlines()[0], seeds=3)
    parser.set_defaults(scenarios=["parking_lot"], noise=[1.5, 3.0])
    parser.add_argument("--target", choices=TARGETS, default="near")
    parser.add_argument("--probe", nargs="+", choices=tuple(PROBES), default=["logistic"])
    parser.add_argument("--features", nargs="+", choices=FEATURE_SETS, default=["obs"],
                        help="the probe's inputs: the observation row, the slot features "
                             "(slot_features.py) or both; one probe per set")
    parser.add_argument("--tuned", action="store_true",
                        help="also play each probe at the threshold of tuned_threshold on "
                             "the last training seed's slots")
    parser.add_argument("--train-seeds", type=int, default=6,
                        help="env seeds 1,000,000 .. + this - 1 to fit the probe on")
    args = parser.parse_args(argv)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    with_slot = any(feature_set != "obs" for feature_set in args.features)
    train: list = []
    last = TRAIN_SEED_BASE + args.train_seeds - 1  # the early-stopping / threshold seed
    for cell in build_grid(args.scenarios, args.noise, [RULE_C],
                           [TRAIN_SEED_BASE + k for k in range(args.train_seeds)], args.steps):
        play_c(cell, list(PAIR), lambda frame, seed=cell.seed: train.append(
            (*probe_rows(frame, args.target, with_slot)[1:4], seed)))
    inputs, labels, gains = (np.concatenate([row[k] for row in train]) for k in range(3))
    held = np.concatenate([np.full(len(row[1]), row[3] == last) for row in train])
    models = {}  # label -> (columns, probe, threshold)
    for feature_set in args.features:
        columns = feature_columns(feature_set, inputs.shape[1], with_slot)
        for name in args.probe:
            model = PROBES[name](inputs[:, columns], labels, held)
            models[column_label(args.target, name, feature_set, False)] = (columns, model, 0.5)
            if args.tuned:
                threshold = tuned_threshold(model(inputs[held][:, columns]), gains[held])
                models[column_label(args.target, name, feature_set, True)] = (
                    columns, model, threshold)
                print(f"{column_label(args.target, name, feature_set, True)}: threshold "
                      f"{threshold:.3f}")
    held_out: list = []
    labels_of = ("headroom_c_c", *models, f"truth_{args.target}")
    with (out / "results.jsonl").open("a") as sink:
        for cell in build_grid(args.scenarios, args.noise, [RULE_C], list(range(args.seeds)),
                               args.steps):
            scored = {label: APAccumulator() for label in labels_of}

            def on_frame(frame: CFrame, scored=scored) -> None:
                slots, rows, truth_labels, _, deviation = probe_rows(frame, args.target,
                                                                     with_slot)
                held_out.append((rows, truth_labels))
                actions = [frame.rule]
                for columns, model, threshold in models.values():
                    action = frame.rule.copy()
                    action[slots[model(rows[:, columns]) >= threshold]] = deviation
                    actions.append(action)
                truth = frame.rule.copy()
                truth[slots[truth_labels]] = deviation
                for accumulator, evaluation in zip(
                        scored.values(), frame.evaluate(np.stack([*actions, truth])),
                        strict=True):
                    accumulator.add_stats(evaluation.stats)
            play_c(cell, list(PAIR), on_frame)
            for label, accumulator in scored.items():
                record_cell(sink, cell, label, {"ap70": accumulator.ap()[0.7]})
    _print_aucs(args, train, held_out, models, with_slot)


def _print_aucs(args, train: list, held_out: list, models: dict, with_slot: bool) -> None:
    """Print the slot and label counts, each probe's held-out AUC, per feature set the
    single input column of the best held-out AUC (either sign), and each slot feature's."""
    inputs = np.concatenate([x for x, _ in held_out])
    labels = np.concatenate([y for _, y in held_out])
    print(f"{args.target} slots: {sum(len(row[1]) for row in train)} training (label 1 on "
          f"{int(sum(row[1].sum() for row in train))}), {len(labels)} held out (label 1 on "
          f"{int(labels.sum())})")
    width = inputs.shape[1]
    names = [f"obs[{j}]" for j in feature_columns("obs", width, with_slot)]
    names += list(NAMES) if with_slot else []
    for label, (columns, model, threshold) in models.items():
        print(f"held-out AUC {label}: {auc(labels, model(inputs[:, columns])):.3f}; "
              f"deviates on {int(np.sum(model(inputs[:, columns]) >= threshold))}")
    for feature_set in args.features:
        single = [(max(value, 1 - value), names[j]) for j in feature_columns(feature_set, width, with_slot)
                  if np.ptp(inputs[:, j]) > 0 for value in [auc(labels, inputs[:, j])]]
        print(f"best single input of {feature_set}: {max(single)[1]} {max(single)[0]:.3f}")
    if with_slot:
        print("held-out AUC of each slot feature (above 0.5: label 1 with larger values): "
              + ", ".join(f"{name} {auc(labels, inputs[:, j]):.3f}" for name, j in zip(
                  NAMES, feature_columns("slot", width, with_slot), strict=True)))


if __name__ == "__main__":
    main()
