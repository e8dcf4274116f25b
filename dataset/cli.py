"""``dtx dataset check | checksum | export | synth | library | redepth``."""

from __future__ import annotations

import argparse
import os
import sys

from dataset.check import check_dataset, content_checksum
from dataset.export import export_pix2pix
from dataset.out_dir import check_apart, write_directory
from dataset.records import DatasetError
from dtx.errors import exit_1_on
from perception.errors import PerceptionError
from perception.surface import DEPTH_MAP_METHODS


def _check(args: argparse.Namespace) -> int:
    report = check_dataset(args.dir)
    print(report.summary())
    return 0 if report.ok else 1


@exit_1_on(DatasetError, OSError)
def _checksum(args: argparse.Namespace) -> int:
    print(f"{content_checksum(args.dir)}  {args.dir}")
    return 0


@exit_1_on(DatasetError, OSError)
def _export(args: argparse.Namespace) -> int:
    if args.format == "pix2pix":
        if len(args.sessions) != 1:
            print("error: --format pix2pix takes one session", file=sys.stderr)
            return 2
        check_apart(args.out, args.sessions)
        counts = write_directory(args.out, args.force, lambda staging: export_pix2pix(args.sessions[0], staging))
        print(f"wrote {sum(counts.values())} A|B images to {args.out}: {counts}")
        return 0
    # A local directory is all the export reads and writes: never ask the Hub (set before the import).
    os.environ.setdefault("HF_HUB_OFFLINE", "1")
    os.environ.setdefault("HF_DATASETS_OFFLINE", "1")
    from dataset.hf_export import export_hf

    counts = export_hf(args.sessions, args.out, force=args.force, progress=True)
    print(
        f"wrote {sum(counts.values())} pairs of {len(args.sessions)} session(s) to {args.out} in the Hugging Face "
        f"layout, read back with datasets.load_dataset: {counts}"
    )
    return 0


@exit_1_on(DatasetError, OSError)
def _synth(args: argparse.Namespace) -> int:
    from dataset.synth import write_synthetic_dataset

    writer = write_synthetic_dataset(args.out, args.samples, args.seed, progress=True)
    print(f"{args.out}: {len(writer)} samples")
    return 0


@exit_1_on(DatasetError, OSError)
def _library(args: argparse.Namespace) -> int:
    from dataset.contact_library import write_contact_library
    from perception.errors import DepthMapError
    from workcell.scene import SceneError

    try:
        writer = write_contact_library(
            args.out,
            args.samples,
            args.seed,
            args.scene,
            tuple(args.depth_range_m),
            progress=True,
            method=args.depth_map,
        )
    except (SceneError, DepthMapError) as err:  # the scene or the depth range given: the caller's input
        print(f"error: {err}", file=sys.stderr)
        return 2
    print(f"{args.out}: {len(writer)} samples")
    return 0


@exit_1_on(DatasetError, PerceptionError, OSError)
def _redepth(args: argparse.Namespace) -> int:
    from pathlib import Path

    from dataset.redepth import density_dirs, redepth_datasets

    targets: dict[float | None, str | Path] = (
        {density: path for density, path in density_dirs(args.dir, args.density).items()} if args.density else {}
    )
    if args.out:
        if len(args.density) > 1:
            print("error: --out takes one density; leave it out to get DIR_density_D for each", file=sys.stderr)
            return 2
        targets = {args.density[0] if args.density else None: args.out}
    if not targets:
        print("error: give --density D [D ...] or --out DIR (full density)", file=sys.stderr)
        return 2
    if args.bins is not None and not args.out:
        print("error: --bins needs --out DIR (the default names say only the density)", file=sys.stderr)
        return 2
    registered = None
    if args.calibration:
        from dataset.registered_again import objects_placed, placement_report

        registered, how = objects_placed(args.dir, args.calibration, jobs=args.jobs)
        print(f"objects {how}")
        for name, row in placement_report(args.dir, registered).items():
            parts = []
            if "moved_mm" in row:
                parts.append(f"moved {row['moved_mm']:.2f} mm {row['moved_deg']:.2f} deg from its recorded pose")
            if "add_s_mm" in row:
                parts.append(f"ADD-S {row['add_s_mm']:.3f} mm against the scene's truth")
            print(f"{name}: {'; '.join(parts)}")
    for density, writer in redepth_datasets(
        args.dir, targets, args.bins, registered=registered, jobs=args.jobs, method=args.depth_map
    ).items():
        print(
            f"{writer.root}: {len(writer)} samples, depth-maps at {'full density' if density is None else f'{density:g} points/cm³'}"
            + ("" if args.bins is None else f", {args.bins} x {args.bins} bins")
            + f", {writer.info.depth_map_method} bins"
        )
    return 0


def add_commands(subparsers: argparse._SubParsersAction) -> None:
    """Add the ``dataset`` command group to the ``dtx`` parser."""
    parser = subparsers.add_parser("dataset", help="check, export or synthesise tactile datasets")
    commands = parser.add_subparsers(dest="dataset_command", required=True)
    _add_check_and_export(commands)
    _add_synth(commands)
    _add_library(commands)
    _add_redepth(commands)


def _add_check_and_export(commands: argparse._SubParsersAction) -> None:
    """``check`` and ``checksum``, each of one dataset directory, and ``export`` of one or more."""
    check = commands.add_parser("check", help="verify every sample; exit 0 only for a sound dataset")
    check.add_argument("dir", help="dataset directory")
    check.set_defaults(func=_check)

    checksum = commands.add_parser(
        "checksum",
        help="SHA-256 of the dataset's content (samples, files, description; "
        "not capture times or code version): equal for two sessions "
        "with the same seed",
    )
    checksum.add_argument("dir", help="dataset directory")
    checksum.set_defaults(func=_checksum)

    export = commands.add_parser(
        "export",
        help="write sessions as a Hugging Face dataset (--format hf: Parquet shards and a dataset card that "
        "datasets.load_dataset(DIR) reads, splits as dtx's) or as aligned A|B images for the reference pix2pix "
        "(--format pix2pix: one session, DIR/train, val, test)",
    )
    export.add_argument("sessions", nargs="+", metavar="SESSION", help="dataset directories (pix2pix: one)")
    export.add_argument("--format", required=True, choices=("hf", "pix2pix"), help="the layout to write")
    export.add_argument("--out", required=True, help="output directory, written beside and renamed into place")
    export.add_argument("--force", action="store_true", help="replace an existing --out directory")
    export.set_defaults(func=_export)


def _add_synth(commands: argparse._SubParsersAction) -> None:
    synth = commands.add_parser("synth", help="render a synthetic dataset of analytic contacts")
    synth.add_argument("out", help="dataset directory to create or resume")
    synth.add_argument("--samples", type=int, default=578, help="number of pairs (default: the paper's 578)")
    synth.add_argument("--seed", type=int, default=0)
    synth.set_defaults(func=_synth)


def _add_library(commands: argparse._SubParsersAction) -> None:
    library = commands.add_parser(
        "library",
        help="render a contact library in a scene's collection geometry "
        "(spheres, cylinders, wedges, corners, textures, height fields)",
    )
    library.add_argument("out", help="dataset directory to create or resume")
    library.add_argument("--samples", type=int, default=1200, help="number of pairs (default 1200)")
    library.add_argument("--seed", type=int, default=0)
    library.add_argument(
        "--scene",
        default="scenes/ycb_three.yaml",
        help="scene whose gripper, GelSight and GelSight effects the pairs are made with",
    )
    library.add_argument(
        "--depth-range-m",
        type=float,
        nargs=2,
        default=(-0.005, 0.01),
        metavar=("NEAR", "FAR"),
        help="depth-map range, as the sessions it trains beside (default -0.005 0.01)",
    )
    library.add_argument(
        "--depth-map",
        choices=DEPTH_MAP_METHODS,
        default="surface",
        help="what a bin holds, as the sessions it trains beside: the object's surface at its centre (default), "
        "or the paper's nearest point",
    )
    library.set_defaults(func=_library)


def _add_redepth(commands: argparse._SubParsersAction) -> None:
    redepth = commands.add_parser(
        "redepth",
        help="make a collected dataset's depth-maps again, e.g. at the "
        "paper's point densities (1 10 20 40 80 points/cm³)",
    )
    redepth.add_argument("dir", help="collected dataset directory")
    redepth.add_argument(
        "--density",
        type=float,
        nargs="+",
        default=[],
        help="points/cm³ after a voxel-grid filter; each goes to DIR_density_D",
    )
    redepth.add_argument("--out", help="output directory for one density (or, without --density, full density)")
    redepth.add_argument(
        "--bins", type=int, help="bins per side (default: the source's); tactile images are resized to match"
    )
    redepth.add_argument(
        "--depth-map",
        choices=DEPTH_MAP_METHODS,
        help="what a bin holds: the object's surface at its centre, or the paper's nearest point (default: the "
        "source's)",
    )
    redepth.add_argument(
        "--calibration",
        help="a calibration directory (dtx calibrate touches): the maps are cut with the objects where its fit "
        "placed them when it was calibrated from this session (placements.json); any other session's objects "
        "are registered again from its camera frames with its extrinsics, turned and placed by its training "
        "touches",
    )
    redepth.add_argument(
        "--jobs",
        type=int,
        default=1,
        help="processes to share the densities, and the touches that choose a turn, out among "
        "(default 1; one per core is fastest)",
    )
    redepth.set_defaults(func=_redepth)
