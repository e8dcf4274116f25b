"""``dtx train``, ``dtx fit-serving`` and ``dtx evaluate``."""

from __future__ import annotations

import argparse
import dataclasses
import os
import sys
import time

from dataset.records import DatasetError
from dtx.errors import exit_1_on
from models.errors import ModelConfigError
from msgs import strict_json


@exit_1_on(ModelConfigError, DatasetError, OSError)
def _train(args: argparse.Namespace) -> int:
    from models.checkpoint import TrainConfig
    from models.train import train

    config = TrainConfig.load(args.config)
    if args.hold_out_object:
        config = dataclasses.replace(config, hold_out_object=args.hold_out_object)
    if args.session_pose_sigma_mm:  # the first is the served default; several: each session's own
        config = config.with_session_pose_sigmas(args.session_pose_sigma_mm, len(args.dataset))
    started = time.monotonic()
    dataset = args.dataset[0] if len(args.dataset) == 1 else args.dataset
    path = train(dataset, config, args.out, resume=args.resume, libraries=args.library)
    if int(os.environ.get("RANK", "0")) == 0:  # under torchrun, one rank fits what is served
        from models.serving import fit_serving

        fit_serving(path)
    print(f"checkpoint {path} ({time.monotonic() - started:.0f} s)")
    return 0


@exit_1_on(ModelConfigError, DatasetError, OSError)
def _fit_serving(args: argparse.Namespace) -> int:
    from models.serving import fit_serving

    figures = fit_serving(args.checkpoint, args.dataset or None)
    print(strict_json.dumps(figures, indent=2) if args.json else f"{args.checkpoint} serves the {figures['serves']}")
    return 0


@exit_1_on(ModelConfigError, DatasetError, OSError)
def _evaluate(args: argparse.Namespace) -> int:
    from models.checkpoint import load_generator
    from models.evaluate import evaluate, summary_table
    from models.figures import write_figures

    if not args.dataset and args.real_presses is None:
        print("error: give a DATASET (or several sessions), --real-presses FILE.npz, or both", file=sys.stderr)
        return 2
    generator, depth_range_m = load_generator(args.checkpoint)
    real: dict | None = None
    if args.real_presses is not None:
        from models.real_presses import (
            evaluate_real_presses,
            real_press_table,
            write_real_press_figure,
        )

        try:
            real, images = evaluate_real_presses(
                generator,
                depth_range_m,
                args.real_presses,
                args.scene,
                args.ball_radius_mm,
                args.mm_per_px,
                seed=args.seed,
            )
        except ModelConfigError as err:  # the presses file or its options: the caller's input
            print(f"error: {err}", file=sys.stderr)
            return 2
        if args.figures:
            write_real_press_figure(real, images, args.figures)
        if not args.dataset:  # real presses alone
            print(strict_json.dumps(real, indent=2) if args.json else real_press_table(real))
            return 0
    from models.evaluate_sessions import evaluate_sessions, sessions_table

    several = len(args.dataset) > 1  # one: exactly the evaluation of one dataset
    result, predictions = (evaluate_sessions if several else evaluate)(
        generator,
        depth_range_m,
        args.dataset if several else args.dataset[0],
        split=args.split,
        hold_out_object=args.hold_out_object,
        density=args.density,
        seed=args.seed,
    )
    if args.figures:
        write_figures(result, predictions, depth_range_m, args.figures)
    if real is not None:
        result["real_presses"] = real
    if args.json:
        print(strict_json.dumps(result, indent=2))
    else:
        table = summary_table(result) + ("\n\n" + sessions_table(result) if several else "")
        print(table + ("" if real is None else "\n\n" + real_press_table(real)))
    return 0


def add_commands(subparsers: argparse._SubParsersAction) -> None:
    """Add ``train``, ``fit-serving`` and ``evaluate`` to the ``dtx`` parser."""
    _add_train(subparsers)
    fit = subparsers.add_parser(
        "fit-serving",
        help="choose what a checkpoint serves (its network or its prior) and fit its uncertainty "
        "(dtx train does this at its end; for a checkpoint trained before)",
    )
    fit.add_argument("checkpoint", help="checkpoint.pt written by dtx train; rewritten in place")
    fit.add_argument(
        "dataset", nargs="*", help="session(s) to fit on (default: the ones the checkpoint was trained on)"
    )
    fit.add_argument("--json", action="store_true", help="print the figures that decided as JSON")
    fit.set_defaults(func=_fit_serving)
    _add_evaluate(subparsers)


def _add_evaluate(subparsers: argparse._SubParsersAction) -> None:
    """``dtx evaluate``."""
    evaluate = subparsers.add_parser("evaluate", help="the paper's SSIM, baseline and template-matching analysis")
    evaluate.add_argument("checkpoint", help="checkpoint.pt written by dtx train")
    evaluate.add_argument(
        "dataset",
        nargs="*",
        help="dataset directory, or several sessions evaluated together and each "
        "(their joint split, as dtx train made it; optional with --real-presses)",
    )
    evaluate.add_argument("--json", action="store_true", help="print the full result as JSON")
    evaluate.add_argument("--figures", metavar="DIR", help="write qualitative.png, ssim_bars.png (and density.png)")
    evaluate.add_argument("--split", default="test", choices=("train", "val", "test", "all"))
    evaluate.add_argument(
        "--hold-out-object",
        default="",
        metavar="NAME",
        help="leave-one-object-out: evaluate on every sample of NAME (train the "
        "checkpoint with hold_out_object: NAME in its config)",
    )
    evaluate.add_argument(
        "--density",
        type=float,
        nargs="+",
        default=[],
        metavar="PTS_PER_CM3",
        help="also evaluate the same pairs with their depth-maps made again from the model cloud "
        "thinned to each density, as dtx dataset redepth --density makes them (the paper's table: 1 10 20 40 80)",
    )
    evaluate.add_argument("--seed", type=int, default=0, help="seed of the baseline's random draws")
    evaluate.add_argument(
        "--real-presses",
        metavar="FILE.npz",
        help="score the model on real GelSight presses of a ball (layout of "
        "assets/gelsight/ball_presses.npz) beside the background, renderer and random frames",
    )
    evaluate.add_argument(
        "--ball-radius-mm", type=float, help="radius of the pressed ball (default: the file's ball_radius_mm, else 2)"
    )
    evaluate.add_argument(
        "--mm-per-px",
        type=float,
        help="pixel pitch of the presses' frames (default: the file's mm_per_px, else 0.1245)",
    )
    evaluate.add_argument(
        "--scene",
        default="scenes/ycb_three.yaml",
        help="scene whose gripper and GelSight the presses are seen with (default ycb_three)",
    )
    evaluate.set_defaults(func=_evaluate)


def _add_train(subparsers: argparse._SubParsersAction) -> None:
    """``dtx train``."""
    train = subparsers.add_parser("train", help="train the cGAN on a dataset's train split (or several sessions')")
    train.add_argument(
        "dataset",
        nargs="+",
        help="dataset directory; several sessions (days of collection) train one model on their "
        "train splits together, each pair with its own session's calibration and depth-maps",
    )
    train.add_argument("--config", required=True, help="training config (YAML), e.g. configs/quick.yaml")
    train.add_argument("--out", default="out/train", help="checkpoint and log directory (default: out/train)")
    train.add_argument("--resume", action="store_true", help="continue from OUT/checkpoint.pt")
    train.add_argument(
        "--hold-out-object",
        default="",
        metavar="NAME",
        help="leave-one-object-out: train without NAME, in every session (overrides the config's hold_out_object)",
    )
    train.add_argument(
        "--session-pose-sigma-mm",
        type=float,
        nargs="+",
        metavar="MM",
        help="the sessions' in-plane pose uncertainty their prior is blurred by, one for all or one a "
        "session (overrides the config's session_pose_sigma_mm; the first is the served default): "
        "smaller for a session redepthed with a touch calibration",
    )
    train.add_argument(
        "--library",
        action="append",
        default=[],
        metavar="DIR",
        help="a contact library (dtx dataset library) whose every sample joins the training set; repeatable",
    )
    train.set_defaults(func=_train)
