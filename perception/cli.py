"""``dtx perception ...`` commands."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

from msgs import strict_json


def add_commands(subparsers: argparse._SubParsersAction) -> None:
    group = subparsers.add_parser("perception", help="segmentation, registration and depth-map tools")
    commands = group.add_subparsers(dest="perception_command", required=True)
    check = commands.add_parser(
        "register-check",
        help="segment and register meshes at random poses in the simulated scene; report accuracy and time",
    )
    check.add_argument("meshes", nargs="+", metavar="MESH", help="mesh files (e.g. assets/ycb/*.obj)")
    check.add_argument("--trials", type=int, default=20, help="random poses per mesh (default 20)")
    check.add_argument("--seed", type=int, default=0)
    check.add_argument("--scene", default="scenes/ycb_three.yaml", help="scene whose cameras and effects are used")
    check.add_argument(
        "--success-add-s-mm",
        type=float,
        default=10.0,
        help="a returned pose counts as a success when its ADD-S is within this (default 10 mm)",
    )
    check.add_argument(
        "--drop-effect",
        action="append",
        default=[],
        metavar="NAME",
        help="switch a scene effect off (repeatable), e.g. extrinsic_offset",
    )
    check.add_argument(
        "--calibration",
        metavar="DIR",
        help="the cameras report this calibration's extrinsics (camera_<name>.yaml, e.g. dtx calibrate touches)",
    )
    check.add_argument("--json", action="store_true", help="print one JSON object keyed by mesh stem")
    check.set_defaults(func=cmd_register_check)


def scene_calibration(scene_path: str, directory: str) -> dict[str, np.ndarray]:
    """Each camera of the scene's camera_to_world from ``directory``/camera_<name>.yaml;
    DepthCameraError when a file is missing or describes another camera."""
    from drivers.depth_camera.base import load_calibration_of
    from msgs import CameraIntrinsics
    from workcell.scene import load_scene

    extrinsics = {}
    for camera in load_scene(scene_path).cameras:
        path = Path(directory) / f"camera_{camera.name}.yaml"
        own = CameraIntrinsics(
            width=camera.width, height=camera.height, fx=camera.fx, fy=camera.fy, cx=camera.cx, cy=camera.cy
        )
        calibration = load_calibration_of(str(path), own, f"{camera.name} of {scene_path}")
        extrinsics[camera.name] = calibration.camera_to_world
    return extrinsics


def cmd_register_check(args: argparse.Namespace) -> int:
    from perception.errors import PerceptionError
    from sim.registration_check import register_check

    missing = [m for m in args.meshes if not Path(m).is_file()]
    if missing:
        print(f"dtx perception register-check: mesh not found: {', '.join(missing)}", file=sys.stderr)
        return 2
    from drivers.depth_camera.base import DepthCameraError

    try:
        report = register_check(
            args.meshes,
            args.trials,
            args.seed,
            args.scene,
            success_add_s_mm=args.success_add_s_mm,
            drop_effects=args.drop_effect,
            calibration=scene_calibration(args.scene, args.calibration) if args.calibration else None,
        )
    except (PerceptionError, DepthCameraError, OSError) as exc:
        print(f"dtx perception register-check: {exc}", file=sys.stderr)
        return 2
    if args.json:
        print(strict_json.dumps(report, indent=2))
        return 0
    for stem, row in report.items():
        print(
            f"{stem:16s} success {row['success_rate']:.0%}  ADD-S median {row['add_s_mm_median']} mm "
            f"p90 {row['add_s_mm_p90']} mm  ADD median {row['add_mm_median']} mm  "
            f"time median {row['time_ms_median']} ms, CPU {row['cpu_ms_median']} ms (segmentation {row['segmentation_ms_median']}, "
            f"coarse {row['coarse_ms_median']}, fine {row['fine_ms_median']})"
        )
    return 0
