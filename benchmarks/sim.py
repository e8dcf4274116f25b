"""Simulated world figures: time per 512 x 424 depth frame with no effects, with each depth
effect alone and with the default effects of ycb_three.yaml (target <= 15 ms per camera
frame); time per GelSight frame at 120 x 160 (<= 3 ms) and 480 x 640 (<= 30 ms) with
sim.gelsight.GelSightRenderer; grasp contact time; and the gelsight-check SSIMs on
assets/gelsight/ball_presses.npz.

Depth frames: the world is static, so each camera's exact ray cast (Open3D
RaycastingScene.cast_rays on all 217k rays at once) is done on the first frame and cached;
the ``first frame`` rows report that full cast, the other rows the steady per-frame cost.
"""

from __future__ import annotations

import argparse
import dataclasses
import statistics
import time
from typing import TYPE_CHECKING

from sim.effects import DEPTH_EFFECT_ORDER

if TYPE_CHECKING:
    from workcell.scene import Scene

SCENE = "scenes/ycb_three.yaml"
# Every effect that changes a depth frame: the depth camera's, in the order they run, and the
# objects' micro-relief.
DEPTH_EFFECTS = (*DEPTH_EFFECT_ORDER, "micro_relief")


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--scene", default=SCENE, help="scene whose default effects are timed")
    parser.add_argument("--camera", default="left")
    parser.add_argument("--frames", type=int, default=30, help="frames timed per configuration")
    parser.add_argument("--skip-check", action="store_true", help="skip the gelsight-check SSIMs")
    parser.add_argument("--check-file", default="assets/gelsight/ball_presses.npz")


def _time(fn, n: int) -> tuple[float, float, float]:
    """(median wall, min wall, median process CPU) time in ms of ``fn`` over ``n`` calls.
    The CPU time (all threads of this process) shows the cost on a machine shared with
    other jobs, where wall time also counts waiting for a core."""
    walls, cpus = [], []
    for _ in range(n):
        c0 = time.process_time()
        t0 = time.perf_counter()
        fn()
        walls.append((time.perf_counter() - t0) * 1e3)
        cpus.append((time.process_time() - c0) * 1e3)
    return statistics.median(walls), min(walls), statistics.median(cpus)


def _row(figure: str, timing: tuple[float, ...], target: float | None = None, unit: str = "ms") -> dict:
    med = timing[0]
    best = timing[1] if len(timing) > 1 else None
    cpu = timing[2] if len(timing) > 2 else None
    row = {
        "figure": figure,
        "value": round(med, 3),
        "best": None if best is None else round(best, 3),
        "cpu": None if cpu is None else round(cpu, 3),
        "unit": unit,
        "target": target,
    }
    row["meets_target"] = None if target is None else bool(med <= target)
    return row


def run(args: argparse.Namespace) -> list[dict]:
    from sim.world import SimWorld

    scene = SimWorld.from_file(args.scene).scene
    ideal = dataclasses.replace(scene, effects=[])
    rows = _depth_rows(scene, ideal, args.camera, args.frames)
    rows += _gelsight_rows(scene, ideal, args.frames)
    if not args.skip_check:
        rows += _check_rows(args.check_file)
    return rows


def _depth_rows(scene: Scene, ideal: Scene, camera: str, frames: int) -> list[dict]:
    """Depth frames with no effects, with each depth effect alone (as the scene sets it, else
    at its defaults) and with the scene's default effects."""
    from sim.effects import EFFECTS
    from workcell.scene import EffectSpec

    rows = _depth_frame_rows("no effects", ideal, camera, frames)
    for name in DEPTH_EFFECTS:
        specs = [e for e in scene.effects if e.name == name]
        if not specs:
            specs = [EffectSpec(name, {k: p.default for k, p in EFFECTS[name].params.items()})]
        rows += _depth_frame_rows(f"{name} alone", dataclasses.replace(scene, effects=specs), camera, frames)
    rows += _depth_frame_rows(f"{scene.name} default effects", scene, camera, frames, target=15.0)
    return rows


def _depth_frame_rows(label: str, scene: Scene, camera: str, frames: int, target: float | None = None) -> list[dict]:
    """The steady time per depth frame of ``camera`` in ``scene``; with no effects also the
    first frame (the full ray cast, cached after)."""
    from sim.world import SimWorld

    world = SimWorld(scene)
    t0 = time.perf_counter()
    world.render_depth(camera)
    first = (time.perf_counter() - t0) * 1e3
    timing = _time(lambda: world.render_depth(camera), frames)
    rows = [_row(f"depth frame 512x424, {label}", timing, target)]
    if label == "no effects":
        rows.append(_row("depth first frame (full ray cast, cached after)", (first,)))
    return rows


def _gelsight_rows(scene: Scene, ideal: Scene, frames: int) -> list[dict]:
    """The grasp contact of both fingers on the scene's second object (no effects), and the
    GelSight frames of its left gap map at 120 x 160 and 480 x 640."""
    from sim.gelsight import GelSightConfig, GelSightRenderer
    from sim.world import SimWorld
    from workcell.kinematics import grasp_to_tcp_pose

    rows = []
    world = SimWorld(ideal)
    verts = world.object_meshes[min(1, len(world.object_meshes) - 1)][0]
    centre = 0.5 * (verts.min(0) + verts.max(0))
    tcp = grasp_to_tcp_pose(centre[0], centre[1], scene.gripper.tcp_to_gel_centre_m + max(0.03, centre[2]), 0.0)
    world.grasp_contact(tcp, 10.0)
    timing = _time(lambda: world.grasp_contact(tcp, 10.0), max(5, frames // 3))
    rows.append(_row("grasp contact, both fingers, 120x160 gap maps", timing))
    contact = world.grasp_contact(tcp, 10.0)
    gap = contact.gap_mm["left"]
    for (h, w), target in (((120, 160), 3.0), ((480, 640), 30.0)):
        renderer = GelSightRenderer(GelSightConfig(image_height=h, image_width=w, mm_per_px=0.1245 * 160 / w))
        g = gap if (h, w) == gap.shape else contact.gap_map("left", (h, w))
        renderer.render(g)
        timing = _time(lambda: renderer.render(g), frames)
        rows.append(_row(f"gelsight frame {h}x{w} (contact of the grasp above)", timing, target))
    return rows


def _check_rows(check_file: str) -> list[dict]:
    """The gelsight-check mean SSIMs of ``check_file``, against their targets."""
    from sim.gelsight_check import run_check

    rows = []
    result = run_check(check_file)
    targets = {"crop": 0.87, "full": 0.92}
    for key, value in result["mean"].items():
        row = {
            "figure": f"gelsight-check SSIM {key}",
            "value": round(float(value), 4),
            "best": None,
            "cpu": None,
            "unit": "SSIM",
            "target": targets.get(key),
        }
        row["meets_target"] = None if key not in targets else bool(value >= targets[key])
        rows.append(row)
    return rows


def main() -> None:  # pragma: no cover - convenience when dtx/cli.py is not there
    from msgs import strict_json

    parser = argparse.ArgumentParser(description=__doc__)
    add_arguments(parser)
    print(strict_json.dumps(run(parser.parse_args()), indent=2))


if __name__ == "__main__":  # pragma: no cover
    main()
