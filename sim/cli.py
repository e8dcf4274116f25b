"""``dtx sim ...`` commands (``dtx/cli.py`` calls :func:`add_commands`)."""

from __future__ import annotations

import argparse
import sys

from msgs import strict_json
from sim.gelsight_effects import GelSightRenderError


def add_commands(subparsers: argparse._SubParsersAction) -> None:
    """Add the ``sim`` group and its subcommands; each sets ``func(args) -> exit status``."""
    sim = subparsers.add_parser("sim", help="the simulated world")
    commands = sim.add_subparsers(dest="sim_command", required=True)
    check = commands.add_parser(
        "gelsight-check",
        help="SSIM of rendered ball presses against real GelSight frames",
        description="Render each ball press of FILE.npz (layout of assets/gelsight/ball_presses.npz) from its "
        "annotated centre and radius (found by the press finder when the file has none) and compare it with "
        "the real frame by SSIM, full frame and a crop of 6 mm of gel (48 x 48 px on the shipped frames), "
        "next to the background and random-frame baselines.",
    )
    check.add_argument(
        "file", metavar="FILE.npz", help="background, frames [touch_center, touch_radius, mm_per_px, ball_radius_mm]"
    )
    check.add_argument("--mm-per-px", type=float, help="the frames' scale (default: the file's, else 0.1245)")
    check.add_argument("--ball-radius-mm", type=float, help="the ball's radius (default: the file's, else 2)")
    check.add_argument("--json", action="store_true", help="print the result as JSON")
    check.add_argument("--seed", type=int, default=0, help="seed of the random-frame baseline (default 0)")
    check.add_argument(
        "--holdout",
        action="store_true",
        help="also refit the renderer's parameters on the even frames and score the odd ones (a minute or two)",
    )
    check.add_argument(
        "--calibration",
        metavar="DIR",
        help="score this calibration directory (dtx calibrate gelsight --out), its background included "
        "(default: the shipped one, against the file's background)",
    )
    check.set_defaults(func=gelsight_check)
    ceiling = commands.add_parser(
        "ceiling",
        help="how well any model could estimate a simulated session's images from its depth-maps",
        description="Render each pair of a simulated session again with what the simulated world knows and "
        "the depth-map hides (the true contact, the micro-relief) and score those estimates like "
        "dtx evaluate scores a model: the ceiling a model's SSIM and dissimilarity ratio can reach.",
    )
    ceiling.add_argument("dataset", help="a session collected on the simulated scene (launch/collect_sim.yaml)")
    ceiling.add_argument("--split", default="test", choices=["train", "val", "test", "all"])
    ceiling.add_argument(
        "--force-n",
        type=float,
        default=None,
        help="grasp force of the session in N (default: its scene's gripper.grasp_force_n, which the "
        "collector commands)",
    )
    ceiling.add_argument("--seed", type=int, default=0, help="seed of the baseline's random draws (default 0)")
    ceiling.add_argument("--json", action="store_true", help="print the result as JSON")
    ceiling.set_defaults(func=information_ceiling)
    shapes = commands.add_parser(
        "shapes",
        help="write the generated thin, flat and symmetric test objects as meshes",
        description="Write the objects of sim/shapes.py (a flat tool, a thin plate, a flat L bracket, a puck, a "
        "disc, a cylinder, a sphere) as DIR/<name>.obj, e.g. for dtx perception register-check DIR/*.obj.",
    )
    shapes.add_argument("directory", metavar="DIR", help="where to write the meshes (made if missing)")
    shapes.add_argument("--only", nargs="+", metavar="NAME", help="write only these shapes")
    shapes.set_defaults(func=write_shape_files)


def gelsight_check(args: argparse.Namespace) -> int:
    from sim.gelsight_check import format_table, run_check

    try:
        result = run_check(
            args.file,
            seed=args.seed,
            holdout=args.holdout,
            calibration_dir=args.calibration,
            mm_per_px=args.mm_per_px,
            ball_radius_mm=args.ball_radius_mm,
        )
    except GelSightRenderError as exc:
        print(f"dtx sim gelsight-check: {exc}", file=sys.stderr)
        return 2
    print(strict_json.dumps(result, indent=2) if args.json else format_table(result))
    return 0


def information_ceiling(args: argparse.Namespace) -> int:
    from dataset.records import DatasetError
    from models.errors import ModelConfigError
    from report.ceiling import CeilingError, format_table
    from report.ceiling import information_ceiling as ceiling

    try:
        result = ceiling(
            args.dataset,
            args.split,
            args.force_n,
            args.seed,
            progress=lambda line: print(f"ceiling: {line}", file=sys.stderr, flush=True),
        )
    except (CeilingError, DatasetError, ModelConfigError) as exc:
        print(f"dtx sim ceiling: {exc}", file=sys.stderr)
        return 2
    print(strict_json.dumps(result, indent=2) if args.json else format_table(result))
    return 0


def write_shape_files(args: argparse.Namespace) -> int:
    from sim.shapes import write_shapes

    try:
        paths = write_shapes(args.directory, args.only)
    except (ValueError, OSError) as exc:
        print(f"dtx sim shapes: {exc}", file=sys.stderr)
        return 2
    print("\n".join(str(path) for path in paths))
    return 0


def main(argv: list[str] | None = None) -> int:
    """``python -m sim.cli sim gelsight-check ...``: the same commands without ``dtx``."""
    parser = argparse.ArgumentParser(prog="dtx")
    add_commands(parser.add_subparsers(dest="command", required=True))
    args = parser.parse_args(argv)
    return args.func(args)


if __name__ == "__main__":
    sys.exit(main())
