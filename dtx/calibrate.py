"""``dtx calibrate touches SESSION --out DIR``: the depth cameras' extrinsics, corrected from the
session's own touches (``dataset.touch_calibration``), written as a calibration directory the
launch files take (``calibration_dir:=DIR``) and ``dtx dataset redepth --calibration`` reads,
with the report beside them (``report.json``, as ``--json`` prints it) and the session's objects as
the fit placed them (``placements.json``: ``dtx dataset redepth --calibration`` of that session
cuts its depth-maps there)."""

from __future__ import annotations

import argparse
import shutil
import tempfile
from pathlib import Path
from typing import Any

from dtx.errors import exit_1_on
from msgs import strict_json


def refuse_existing(out: Path, force: bool) -> None:
    """FileExistsError for an existing calibration directory ``out`` unless ``force``."""
    if out.exists() and not force:
        raise FileExistsError(f"{out} exists; give --force to replace it (it is replaced whole, never half-way)")


def write_calibration_dir(out: Path, files: dict[str, str] | dict[str, bytes], force: bool) -> None:
    """The files into ``out`` as one step: written beside it, then renamed into place, so a
    failure leaves any existing directory as it was. An existing ``out`` needs ``force``."""
    refuse_existing(out, force)
    out.parent.mkdir(parents=True, exist_ok=True)
    staging = Path(tempfile.mkdtemp(prefix=f".{out.name}.", dir=out.parent))
    try:
        for name, content in files.items():
            if isinstance(content, bytes):
                (staging / name).write_bytes(content)
            else:
                (staging / name).write_text(content)
        if out.exists():
            retired = Path(tempfile.mkdtemp(prefix=f".{out.name}.old.", dir=out.parent))
            out.rename(retired / out.name)
            staging.rename(out)
            shutil.rmtree(retired)
        else:
            staging.rename(out)
    finally:
        if staging.exists():
            shutil.rmtree(staging)


def _print_report(report: dict[str, Any], out: Path) -> None:
    print(f"{'camera':8} {'correction mm':>13} {'point residual mm':>17}  error against the scene's truth")
    for name, row in report["cameras"].items():
        error = (
            f"{row['error_before_mm']:.2f} mm {row['error_before_deg']:.3f} deg -> {row['error_mm']:.2f} mm "
            f"{row['error_deg']:.3f} deg"
            if "error_mm" in row
            else "(none: a real cell)"
        )
        residual = "none on a model" if row["point_residual_mm"] is None else f"{row['point_residual_mm']:.2f}"
        print(f"{name:8} {row['correction_mm']:13.2f} {residual:>17}  {error}")
        if row["unobservable"]:
            print(f"warning: camera {name}: the touches and views leave {', '.join(row['unobservable'])} unpinned")
    print(f"{'object':18} {'touches':>7} {'outliers':>8}  touch offset mm before -> after")
    for name, row in report["objects"].items():
        print(
            f"{name:18} {row['touches']:7d} {row['outliers']:8d}  {row['offset_before_mm']:.2f} -> {row['offset_after_mm']:.2f}"
        )
    print(f"touches without contact the renderer can place (left out): {report['no_contact_touches']}")
    print(f"wrote {out}")


def _touches(args: argparse.Namespace) -> int:
    from dataset.reader import DatasetReader  # noqa: PLC0415 - Open3D and the renderer load with it
    from dataset.registered_again import PLACEMENTS_FILE, placements_file  # noqa: PLC0415
    from dataset.touch_calibration import calibrate_touches, scene_camera_truth  # noqa: PLC0415
    from drivers.depth_camera.base import Calibration, calibration_yaml  # noqa: PLC0415

    refuse_existing(Path(args.out), args.force)  # before minutes of work, and again when writing
    result = calibrate_touches(args.session, grasps=args.grasps, jobs=args.jobs)
    report = result.report(scene_camera_truth(DatasetReader(args.session).info.scene))
    files = {
        f"{frame_id}.yaml": calibration_yaml(
            Calibration(frame_id.removeprefix("camera_"), image.intrinsics, image.camera_to_world),
            f"{frame_id}, corrected by `dtx calibrate touches {args.session}` from the training split's touches",
        )
        for frame_id, image in result.calibrated.items()
    }
    files["report.json"] = strict_json.dumps(report, indent=1) + "\n"
    files[PLACEMENTS_FILE] = placements_file(args.session, result.cell.objects)
    write_calibration_dir(Path(args.out), files, args.force)
    if args.json:
        print(strict_json.dumps(report))
    else:
        _print_report(report, Path(args.out))
    return 0


def add_commands(subparsers: argparse._SubParsersAction) -> None:
    """Add the ``calibrate`` command group to the ``dtx`` parser."""
    from dataset.records import DatasetError  # noqa: PLC0415
    from perception.errors import PerceptionError  # noqa: PLC0415

    parser = subparsers.add_parser("calibrate", help="calibrate the cell's sensors from a session or from ball presses")
    commands = parser.add_subparsers(dest="calibrate_command", required=True)
    touches = commands.add_parser(
        "touches", help="correct the depth cameras' extrinsics from a session's touches (training split)"
    )
    touches.add_argument("session", help="a collected session (dataset directory with its session.mcap)")
    touches.add_argument("--out", required=True, help="calibration directory to write (camera_<name>.yaml)")
    touches.add_argument("--force", action="store_true", help="replace an existing --out directory")
    touches.add_argument(
        "--grasps", type=int, metavar="N", help="use the touches of the session's first N grasps only (robot time)"
    )
    touches.add_argument(
        "--jobs", type=int, default=1, help="processes to fit the touches in (default 1; one per core is fastest)"
    )
    touches.add_argument("--json", action="store_true", help="the report as JSON")
    touches.set_defaults(func=exit_1_on(DatasetError, PerceptionError, FileExistsError, OSError)(_touches))
    _add_gelsight(commands)
    _add_uncertainty(commands)


def _gelsight(args: argparse.Namespace) -> int:
    from sim.gelsight_calibrate import calibrate_presses, calibration_files, format_report  # noqa: PLC0415

    refuse_existing(Path(args.out), args.force)  # before minutes of work, and again when writing
    fit, presses, report = calibrate_presses(args.presses, args.folds, args.mm_per_px, args.ball_radius_mm)
    files = calibration_files(fit, presses)
    files["report.json"] = (strict_json.dumps(report, indent=1) + "\n").encode()
    write_calibration_dir(Path(args.out), files, args.force)
    if args.json:
        print(strict_json.dumps(report))
        return 0
    h, w = report["frame_shape"]
    print(format_report(report) + f"\nwrote {args.out}")
    print(
        f"a scene renders this sensor with gelsight: {{image_height: {h}, image_width: {w}, "
        f"mm_per_px: {report['mm_per_px']:g}, calibration_dir: {args.out}}}"
    )
    return 0


def _add_gelsight(commands: argparse._SubParsersAction) -> None:
    from sim.gelsight_effects import GelSightRenderError  # noqa: PLC0415

    gelsight = commands.add_parser(
        "gelsight",
        help="fit the GelSight renderer's photometric model from ball presses of the lab's sensor",
        description="Find each press's centre and radius, fit the colour of each surface slope, the background "
        "and the renderer's physical parameters, report k-fold scores on presses each fit never saw, and write "
        "a calibration directory (gelsight: calibration_dir: DIR in a scene file).",
    )
    _add_press_arguments(gelsight, "calibration directory to write", "directory")
    gelsight.add_argument("--folds", type=int, default=3, metavar="K", help="k-fold split of the presses (default 3)")
    gelsight.set_defaults(func=exit_1_on(GelSightRenderError, FileExistsError, OSError)(_gelsight))


def _uncertainty(args: argparse.Namespace) -> int:
    from models.calibrate_uncertainty import calibrate_sensor_floor  # noqa: PLC0415
    from models.uncertainty import uncertainty_table  # noqa: PLC0415

    options = {"scene": args.scene, "ball_radius_mm": args.ball_radius_mm, "mm_per_px": args.mm_per_px}
    report = calibrate_sensor_floor(args.checkpoint, args.presses, args.out, args.force, **options)
    if args.json:
        print(strict_json.dumps(report))
        return 0
    presses = report["presses"]
    print(
        f"sensor floor from {presses['presses']} presses of {presses['file']}: mean {report['floor_mean_levels']:.2f}, "
        f"most {report['floor_max_levels']:.2f} levels"
    )
    print("u on these presses as the checkpoint served it:")
    print("\n".join(uncertainty_table(report["served_before"])))
    if report["leave_one_out"] is not None:
        print("u with the floor, each press's fitted on the other presses:")
        print("\n".join(uncertainty_table(report["leave_one_out"])))
    print(f"wrote {report['out']}: it serves this sensor (dtx launch launch/serve.yaml checkpoint:={report['out']})")
    return 0


def _add_uncertainty(commands: argparse._SubParsersAction) -> None:
    from models.errors import ModelConfigError  # noqa: PLC0415

    uncertainty = commands.add_parser(
        "uncertainty",
        help="give a checkpoint's served uncertainty the floor of the lab's own GelSight, from its ball presses",
        description="Serve the checkpoint on the presses, fit per pixel the sensor's error beyond the checkpoint's "
        "u (the light that changes frame to frame), report u on each press with the floor fitted on the others, "
        "and write the checkpoint with the floor to --out: every reply of it then carries sqrt(u^2 + floor^2).",
    )
    uncertainty.add_argument("checkpoint", help="a checkpoint that serves an uncertainty (dtx fit-serving)")
    _add_press_arguments(uncertainty, "the checkpoint to write (the input is left as it is)", "checkpoint")
    uncertainty.add_argument(
        "--scene",
        default="scenes/ycb_three.yaml",
        help="scene whose gripper and GelSight the presses are seen with, as dtx evaluate takes it (default ycb_three)",
    )
    uncertainty.set_defaults(func=exit_1_on(ModelConfigError, FileExistsError, OSError)(_uncertainty))


def _add_press_arguments(parser: argparse.ArgumentParser, out_help: str, out_kind: str) -> None:
    """What every command fitted on a lab's ball presses takes: the file, its scale and ball, --out."""
    parser.add_argument(
        "presses", metavar="PRESSES.npz", help="background, frames (layout of assets/gelsight/ball_presses.npz)"
    )
    parser.add_argument("--out", required=True, help=out_help)
    parser.add_argument("--mm-per-px", type=float, help="the frames' scale (default: the file's mm_per_px)")
    parser.add_argument("--ball-radius-mm", type=float, help="the ball's radius (default: the file's ball_radius_mm)")
    parser.add_argument("--force", action="store_true", help=f"replace an existing --out {out_kind}")
    parser.add_argument("--json", action="store_true", help="the report as JSON")
