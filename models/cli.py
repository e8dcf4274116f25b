"""``dtx train`` and ``dtx evaluate``."""
from __future__ import annotations

import argparse
import dataclasses
import json
import time

from dataset.format import DatasetError
from dtx.errors import exit_1_on
from models.errors import ModelConfigError


@exit_1_on(ModelConfigError, DatasetError, OSError)
def _train(args: argparse.Namespace) -> int:
    from models.train import TrainConfig, train  # noqa: PLC0415 (torch import only when used)

    config = TrainConfig.load(args.config)
    if args.hold_out_object:
        config = dataclasses.replace(config, hold_out_object=args.hold_out_object)
    started = time.monotonic()
    path = train(args.dataset, config, args.out, resume=args.resume)
    print(f"checkpoint {path} ({time.monotonic() - started:.0f} s)")
    return 0


@exit_1_on(ModelConfigError, DatasetError, OSError)
def _evaluate(args: argparse.Namespace) -> int:
    from models.evaluate import evaluate, parse_density, summary_table, write_figures  # noqa: PLC0415
    from models.train import load_generator  # noqa: PLC0415

    generator, depth_range_m = load_generator(args.checkpoint)
    result, predictions = evaluate(generator, depth_range_m, args.dataset, split=args.split,
                                   hold_out_object=args.hold_out_object, density=parse_density(args.density),
                                   seed=args.seed)
    if args.figures:
        write_figures(result, predictions, depth_range_m, args.figures)
    print(json.dumps(result, indent=2) if args.json else summary_table(result))
    return 0


def add_commands(subparsers: argparse._SubParsersAction) -> None:
    """Add ``train`` and ``evaluate`` to the ``dtx`` parser."""
    train = subparsers.add_parser("train", help="train the cGAN on a dataset's train split")
    train.add_argument("dataset", help="dataset directory")
    train.add_argument("--config", required=True, help="training config (YAML), e.g. configs/quick.yaml")
    train.add_argument("--out", default="out/train", help="checkpoint and log directory (default: out/train)")
    train.add_argument("--resume", action="store_true", help="continue from OUT/checkpoint.pt")
    train.add_argument("--hold-out-object", default="", metavar="NAME",
                       help="leave-one-object-out: train without NAME (overrides the config's hold_out_object)")
    train.set_defaults(func=_train)

    evaluate = subparsers.add_parser("evaluate", help="the paper's SSIM, baseline and template-matching analysis")
    evaluate.add_argument("checkpoint", help="checkpoint.pt written by dtx train")
    evaluate.add_argument("dataset", help="dataset directory")
    evaluate.add_argument("--json", action="store_true", help="print the full result as JSON")
    evaluate.add_argument("--figures", metavar="DIR", help="write qualitative.png, ssim_bars.png (and density.png)")
    evaluate.add_argument("--split", default="test", choices=("train", "val", "test", "all"))
    evaluate.add_argument("--hold-out-object", default="", metavar="NAME",
                          help="leave-one-object-out: evaluate on every sample of NAME (train the "
                               "checkpoint with hold_out_object: NAME in its config)")
    evaluate.add_argument("--density", action="append", default=[], metavar="PTS_PER_CM3=DIR",
                          help="a dataset made from clouds downsampled to that density; repeat for the "
                               "paper's table (1, 10, 20, 40, 80)")
    evaluate.add_argument("--seed", type=int, default=0, help="seed of the baseline's random draws")
    evaluate.set_defaults(func=_evaluate)
