"""``roco-env scenario``: list scenarios, generate stress scenarios (logic in
roco_env.traffic.generate)."""

from __future__ import annotations

import argparse

from roco_env.scenario import SOURCE_LAYOUTS, list_scenarios


def register(subparsers: argparse._SubParsersAction) -> None:
    parser = subparsers.add_parser("scenario", help="list scenarios or generate stress scenarios")
    actions = parser.add_subparsers(dest="scenario_command", metavar="ACTION", required=True)
    actions.add_parser("list", help="names of the available scenarios").set_defaults(func=_list)
    gen = actions.add_parser(
        "generate", help="write a crowded synthetic scenario YAML and print a summary")
    gen.add_argument("--layout", required=True,
                     help=" | ".join(SOURCE_LAYOUTS["synthetic"]))
    gen.add_argument("--density", type=float, required=True,
                     help="vehicles per 100 m of lane (parking_lot: stall fill ratio 0..1)")
    gen.add_argument("--cavs", type=int, default=4)
    gen.add_argument("--rsus", type=int, default=1)
    gen.add_argument("--seed", type=int, default=0, help="seed of the previewed episode")
    gen.add_argument("--min-gap", type=float, default=None, help="spawn gap, m (default: tight)")
    gen.add_argument("-o", "--output", required=True, help="scenario YAML to write")
    gen.add_argument("--export-opv2v", metavar="DIR", default=None,
                     help="also write the preview episode as OPV2V label folders")
    gen.add_argument("--frames", type=int, default=None,
                     help="frames to export with --export-opv2v (default 10)")
    gen.add_argument("--overwrite", action="store_true",
                     help="replace an earlier export in --export-opv2v DIR (a non-empty DIR "
                     "is refused otherwise)")
    gen.set_defaults(func=_generate)


def _list(args: argparse.Namespace) -> int:
    print("\n".join(list_scenarios()))
    return 0


def _generate(args: argparse.Namespace) -> int:
    from roco_env.traffic.generate import EXPORT_FRAMES, generate

    if args.export_opv2v is None:
        for option, given in (("--frames", args.frames is not None),
                              ("--overwrite", args.overwrite)):
            if given:
                raise ValueError(f"{option} only applies with --export-opv2v DIR")
    frames = EXPORT_FRAMES if args.frames is None else args.frames
    config, summary = generate(args.layout, args.density, args.cavs, args.rsus, args.seed,
                               output=args.output, export_dir=args.export_opv2v,
                               frames=frames, min_gap=args.min_gap,
                               overwrite=args.overwrite)
    print(f"wrote {args.output} ({config.name})")
    for line in summary.lines():
        print(line)
    if args.export_opv2v:
        from roco_env.traffic.opv2v_export import scenario_folder

        print(f"exported {frames} frames to {scenario_folder(args.export_opv2v)} (OpenCOOD "
              f"layout <dir>/<split>/<scenario>; replay with traffic.path=that folder)")
    return 0
