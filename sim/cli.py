"""``dtx sim ...`` commands (``dtx/cli.py`` calls :func:`add_commands`)."""
from __future__ import annotations

import argparse
import json
import sys

from sim.gelsight_effects import GelSightError


def add_commands(subparsers: argparse._SubParsersAction) -> None:
    """Add the ``sim`` group and its subcommands; each sets ``func(args) -> exit status``."""
    sim = subparsers.add_parser("sim", help="the simulated world")
    commands = sim.add_subparsers(dest="sim_command", required=True)
    check = commands.add_parser(
        "gelsight-check", help="SSIM of rendered ball presses against real GelSight frames",
        description="Render each ball press of FILE.npz (layout of assets/gelsight/ball_presses.npz) from its "
                    "annotated centre and radius and compare it with the real frame by SSIM, full frame and "
                    "48x48 crop, next to the background and random-frame baselines.")
    check.add_argument("file", metavar="FILE.npz", help="background, frames, touch_center, touch_radius")
    check.add_argument("--json", action="store_true", help="print the result as JSON")
    check.add_argument("--seed", type=int, default=0, help="seed of the random-frame baseline (default 0)")
    check.add_argument("--holdout", action="store_true",
                       help="also refit the renderer's parameters on the even frames and score the odd ones "
                            "(a minute or two)")
    check.set_defaults(func=gelsight_check)


def gelsight_check(args: argparse.Namespace) -> int:
    from sim.gelsight_check import format_table, run_check  # noqa: PLC0415 (loads scipy/skimage only here)

    try:
        result = run_check(args.file, seed=args.seed, holdout=args.holdout)
    except GelSightError as exc:
        print(f"dtx sim gelsight-check: {exc}", file=sys.stderr)
        return 2
    print(json.dumps(result, indent=2) if args.json else format_table(result))
    return 0


def main(argv: list[str] | None = None) -> int:
    """``python -m sim.cli sim gelsight-check ...``: the same commands without ``dtx``."""
    parser = argparse.ArgumentParser(prog="dtx")
    add_commands(parser.add_subparsers(dest="command", required=True))
    args = parser.parse_args(argv)
    return args.func(args)


if __name__ == "__main__":
    sys.exit(main())
