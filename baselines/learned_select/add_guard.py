"""Give a select-mode weights file a guard (roco_env.policies.learned.Guard).

    python baselines/learned_select/add_guard.py IN.pt OUT.pt --reject-margin M [--keep roco_antialias]

The guarded policy takes ``--keep`` (a name of the default ``action.choices``) for every
slot and lets the network reject only the slots that choice left untested (no
significance statistic computed); ``M`` (logits)
is how far the reject logit may trail the kept choice's and still win. The network's
tensors are copied unchanged; the metadata gains ``guard`` and records this step
(``guarded``). Read with ``weights_only=True``.
"""

from __future__ import annotations

import argparse
import json

import torch

from roco_env.scenario import ActionConfig


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("source")
    parser.add_argument("target")
    parser.add_argument("--reject-margin", type=float, required=True)
    parser.add_argument("--keep", default="roco_antialias")
    args = parser.parse_args(argv)
    raw = torch.load(args.source, map_location="cpu", weights_only=True)
    metadata = json.loads(raw["metadata"])
    choices = list(metadata["env_overrides"].get("action.choices", ActionConfig().choices))
    if args.keep not in choices:
        raise SystemExit(f"--keep {args.keep!r} is not one of action.choices {choices}")
    metadata["guard"] = {"keep": choices.index(args.keep), "reject_margin": args.reject_margin}
    metadata["guarded"] = (f"add_guard.py --keep {args.keep} --reject-margin "
                           f"{args.reject_margin:g} on {args.source}")
    torch.save({"state_dict": raw["state_dict"], "metadata": json.dumps(metadata, sort_keys=True)},
               args.target)


if __name__ == "__main__":
    main()
