"""Can the observation tell where to deviate from hand rule C? (privileged probe, not shipped)

    nice -n 10 python baselines/learned_select/choice_probe.py --out runs/near_probe \
        [--target near] [--probe logistic] [--scenarios parking_lot] [--noise 1.5 3.0] \
        [--train-seeds 6] [--seeds 3]

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
slots the probe gives p > 0.5; ``probe_<target>_mlp`` for the MLP) and
``truth_<target>`` (C, deviating on every slot whose label is 1). Writes ``results.jsonl`` (``table.py``) and prints the held-out AUC of the
probe and of the single best input column, with the slot and label counts.
"""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path

import numpy as np
from env_hook import record_cell
from headroom_c import PAIR, RULE_C, WITHIN_M, CFrame, play_c
from privileged_bound import grid_parser

from roco_env.metrics import APAccumulator
from roco_env.sweeps.cells import build_grid
from roco_env.training.rl.curriculum import TRAIN_SEED_BASE

TARGETS = ("near", "reject")
L2 = 1.0  # the logistic regression's penalty on the weights (standardised inputs)
ITERATIONS, STEP = 3000, 0.5  # its full-batch gradient descent
EPOCHS, CHECK_EVERY = 1000, 25  # the MLP's full-batch Adam epochs, early-stopping checks
Probe = Callable[[np.ndarray], np.ndarray]  # (N, D) inputs -> (N,) probability of label 1


def probe_rows(frame: CFrame, target: str) -> tuple[np.ndarray, np.ndarray, np.ndarray, int]:
    """(slots (k,), inputs (k, D), labels (k,) bool, the deviation's select index) of
    ``frame``'s slots ``target`` may deviate on (module docstring): each slot's
    observation row and its label."""
    tested = ~frame.untested
    if target == "near":
        slots = np.flatnonzero(tested & (frame.gap <= WITHIN_M))
        labels, deviation = frame.errors[0, slots] < frame.errors[1, slots], 0
    else:
        slots, deviation = np.flatnonzero(tested), len(frame.errors)
        trials = np.repeat(frame.rule[None], len(slots) + 1, axis=0)
        trials[1 + np.arange(len(slots)), slots] = deviation
        ap = np.nan_to_num(frame.frame_ap(trials), nan=-1.0)
        labels = ap[1:] > ap[0]
    observation = frame.observation
    pair = observation["choice_diagnostics"][slots, :2]
    inputs = np.concatenate([pair.reshape(len(slots), 2 * pair.shape[2]),
                             observation["diagnostics"][slots]], axis=1)
    return slots, inputs.astype(float), labels, deviation


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


def main(argv: list[str] | None = None) -> None:
    parser = grid_parser(__doc__.splitlines()[0], seeds=3)
    parser.set_defaults(scenarios=["parking_lot"], noise=[1.5, 3.0])
    parser.add_argument("--target", choices=TARGETS, default="near")
    parser.add_argument("--probe", choices=tuple(PROBES), default="logistic")
    parser.add_argument("--train-seeds", type=int, default=6,
                        help="env seeds 1,000,000 .. + this - 1 to fit the probe on")
    args = parser.parse_args(argv)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    train: list = []
    last = TRAIN_SEED_BASE + args.train_seeds - 1  # the MLP's early-stopping seed
    for cell in build_grid(args.scenarios, args.noise, [RULE_C],
                           [TRAIN_SEED_BASE + k for k in range(args.train_seeds)], args.steps):
        play_c(cell, list(PAIR), lambda frame, seed=cell.seed: train.append(
            (*probe_rows(frame, args.target)[1:3], seed)))
    model = PROBES[args.probe](
        np.concatenate([x for x, _, _ in train]), np.concatenate([y for _, y, _ in train]),
        np.concatenate([np.full(len(y), seed == last) for _, y, seed in train]))
    held_out: list = []
    labels_of = ("headroom_c_c", f"probe_{args.target}"
                 + ("" if args.probe == "logistic" else f"_{args.probe}"), f"truth_{args.target}")
    with (out / "results.jsonl").open("a") as sink:
        for cell in build_grid(args.scenarios, args.noise, [RULE_C], list(range(args.seeds)),
                               args.steps):
            scored = {label: APAccumulator() for label in labels_of}

            def on_frame(frame: CFrame, scored=scored) -> None:
                slots, inputs, labels, deviation = probe_rows(frame, args.target)
                held_out.append((inputs, labels))
                probe, truth = frame.rule.copy(), frame.rule.copy()
                probe[slots[model(inputs) > 0.5]] = deviation
                truth[slots[labels]] = deviation
                for accumulator, evaluation in zip(
                        scored.values(), frame.evaluate(np.stack([frame.rule, probe, truth])),
                        strict=True):
                    accumulator.add_stats(evaluation.stats)
            play_c(cell, list(PAIR), on_frame)
            for label, accumulator in scored.items():
                record_cell(sink, cell, label, {"ap70": accumulator.ap()[0.7]})
    inputs = np.concatenate([x for x, _ in held_out])
    labels = np.concatenate([y for _, y in held_out])
    columns = [auc(labels, inputs[:, j]) for j in range(inputs.shape[1])
               if np.ptp(inputs[:, j]) > 0]
    print(f"{args.target} slots: {sum(len(y) for _, y, _ in train)} training (label 1 on "
          f"{int(sum(y.sum() for _, y, _ in train))}), {len(labels)} held out (label 1 on "
          f"{int(labels.sum())}); held-out AUC: {args.probe} probe "
          f"{auc(labels, model(inputs)):.3f}, "
          f"best single input {max(max(columns), 1 - min(columns)):.3f}")


if __name__ == "__main__":
    main()
