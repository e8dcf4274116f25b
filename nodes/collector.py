"""Collector node: Algorithm 1 of the paper, end to end, through the other nodes' services.

For each object: register it (``/perception/register``). For each grasp: draw (x, y, z,
theta_z) = registered centroid + a seeded random offset (palm parallel to the table, only theta_z
free), approach from above (the fingers opening on the way), close the gripper on the object's
nominal width (the registered model's extent across the fingers at the drawn grasp: a WSG looks
for the part only within its clamping travel around that width) to the constant contact force,
wait for both GelSight frames at contact while both fingers' depth-maps are cut (``/perception/patch``),
write one (tactile image, depth-map) pair per finger while the fingers release and the arm retreats.

Policy for what goes wrong (counted, never a half sample): a draw where an open finger would
land on the registered model, whose fingers find nothing, or whose gel does not reach the model,
is retried with a fresh draw, up to ``max_attempts``, then skipped. A device or node that fails (a service time-out, a
respawned node) makes the collector wait for it and redo the grasp with the same draw. A
grasp's two pairs land in the dataset together, in one write, once both are in hand; a
resumed session first drops any lone finger (an append torn by a crash) and redoes that grasp
whole, so no grasp pairs fingers of two attempts. Every draw is seeded by (seed, grasp id,
attempt), so a resumed session redoes exactly the grasps that are missing. The session ends
with ``dtx dataset check`` on what it wrote: its last line says whether the dataset passed,
and a failed check ends the collector (and the launch) with a non-zero status.
"""

from __future__ import annotations

import contextlib
import dataclasses
import functools
import json
import os
import time
from collections.abc import Callable, Iterator
from concurrent.futures import Future, wait
from pathlib import Path
from typing import Any, NoReturn

import numpy as np

import msgs
from bus.node import EXIT_DO_NOT_RESPAWN, Node, run_node
from bus.services import ServiceCallError
from dataset.announced import write_samples
from dataset.check import check_dataset
from dataset.images import resize_rgb, subtract_background
from dataset.records import DatasetError, DatasetInfo, code_version
from dataset.writer import DatasetWriter
from msgs.progress import Progress
from msgs.system import ErrorCode
from perception.pointcloud import transform_points
from perception.registration import sample_model_cloud
from workcell.kinematics import across_the_gels_m, gel_poses_world, grasp_to_tcp_pose
from workcell.scene import load_scene

FINGERS = ("left", "right")


class GraspFailed(Exception):
    """This draw gave no usable contact; another draw may."""


@dataclasses.dataclass
class Stats:
    grasps_done: int = 0
    pairs_written: int = 0
    failed_draws: int = 0
    device_retries: int = 0
    skipped: int = 0


class CollectorNode(Node):
    @dataclasses.dataclass
    class Params:
        out: str = "out/session"
        grasps: int = 289
        seed: int = 0
        scene: str = "scenes/ycb_three.yaml"
        objects: list = dataclasses.field(default_factory=list)  # default: every mesh object of the scene
        resume: bool = False
        offset_xy_m: float = 0.015
        offset_closing_m: float = 0.003
        offset_z_m: float = 0.02
        approach_height_m: float = 0.08
        min_gel_height_m: float = 0.006  # lowest edge of the gel above the table
        finger_clearance_m: float = 0.0  # least room between the model and an open gel's face
        gripper_speed_m_s: float = 0.4
        arm_speed_m_s: float = 0.25
        arm_accel_m_s2: float = 1.2
        settle_s: float = 0.05
        max_attempts: int = 5
        call_timeout_s: float = 10.0
        node_wait_s: float = 60.0
        tactile_topics: list = dataclasses.field(
            default_factory=lambda: ["/gelsight_left/image", "/gelsight_right/image"]
        )

    def __init__(self, name: str, params: dict[str, Any] | None = None, **kwargs: Any) -> None:
        super().__init__(name, params, **kwargs)
        p = self.params
        if p.grasps < 1:
            raise ValueError(f"grasps must be at least 1, got {p.grasps}")
        self.scene = load_scene(p.scene)
        meshes = [o.name for o in self.scene.objects if o.mesh]
        self.objects = list(p.objects) or meshes
        unknown = sorted(set(self.objects) - set(meshes))
        if unknown:
            raise ValueError(f"objects {unknown} are not in {p.scene}; it has {meshes}")
        self.geometry = self.scene.gripper_geometry()
        if not 0.0 <= p.finger_clearance_m < self.geometry.max_width_m / 2:  # NaN fails too
            raise ValueError(f"finger_clearance_m must be in [0, half the open width) m, got {p.finger_clearance_m!r}")
        out = Path(p.out)
        try:
            out.mkdir(parents=True, exist_ok=True)
        except OSError as error:
            raise ValueError(f"cannot create the output directory {out}: {error}") from error
        respawned = int(os.environ.get("DTX_RESPAWN", "0")) > 0
        if (out / "manifest.jsonl").exists() and not (p.resume or respawned):
            raise ValueError(f"{out} already holds a dataset; pass resume:=true to continue it, or choose another out")
        # A new dataset is created with the first pair, whose depth-map says the normalisation range.
        self.writer: DatasetWriter | None = self.open_writer() if (out / "dataset.json").exists() else None
        if self.writer is not None:
            dropped = self.drop_incomplete_grasps(self.writer)
            if dropped:
                self.log.warning(
                    "dropped lone finger sample(s) %s (a crash between a grasp's writes); "
                    "their grasps are redone whole",
                    dropped,
                )
        self.tactile: dict[str, msgs.TactileImage] = {}
        for finger, topic in zip(FINGERS, p.tactile_topics, strict=True):
            self.create_subscription(topic, msgs.TactileImage, functools.partial(self.tactile.__setitem__, finger))
        self.grip_seen_ns = 0  # when /gripper/state first reported the current grip
        self.create_subscription("/gripper/state", msgs.GripperState, self.on_gripper_state)
        self.move = self.create_client("/arm/move", msgs.ArmMoveRequest, msgs.ArmState)
        self.gripper = self.create_client("/gripper/command", msgs.GripperCommand, msgs.GripperState)
        self.register = self.create_client("/perception/register", msgs.RegisterRequest, msgs.RegisterReply)
        self.patch = self.create_client("/perception/patch", msgs.PatchRequest, msgs.PatchReply)
        self.samples = self.create_publisher("/collector/sample", msgs.DatasetSample)
        self.stats = Stats()
        self.stage_s: dict[str, list[float]] = {}
        self.registered: dict[str, msgs.RegisterReply] = {}
        self.last_arm: msgs.ArmState | None = None
        self.releasing: Future[None] | None = None  # the release begun while a grasp was written
        self.model_points: dict[str, np.ndarray] = {}  # model frame, m; for the nominal width

    # -- the session ---------------------------------------------------------------------
    def grasp_plan(self) -> list[tuple[int, str]]:
        """(grasp id, object) for the whole session: consecutive blocks per object."""
        per_object, extra = divmod(self.params.grasps, len(self.objects))
        plan: list[tuple[int, str]] = []
        for index, name in enumerate(self.objects):
            plan += [(len(plan) + i, name) for i in range(per_object + (1 if index < extra else 0))]
        return plan

    def written(self, sample_id: str) -> bool:
        return self.writer is not None and sample_id in self.writer

    def spin(self, until: Any = None) -> None:  # the session replaces the idle executor loop
        plan = self.grasp_plan()
        todo = [(g, o) for g, o in plan if not all(self.written(self.sample_id(g, f)) for f in FINGERS)]
        self.stats.grasps_done = len(plan) - len(todo)
        done = self.stats.grasps_done
        self.log.info(
            "session: %d grasps of %s into %s (%d already there)", len(plan), self.objects, self.params.out, done
        )
        self.wait_for_nodes()
        self.started = time.monotonic()
        # A line per grasp on a terminal, as ever; through a file or pipe, a line every tenth or 10 s.
        with Progress("collect", len(plan), "grasps", initial=len(plan) - len(todo), bar_on_terminal=False) as progress:
            for grasp_id, object_name in todo:
                if self.shutting_down:
                    self.log.info("stopped by request after %d grasps; resume:=true continues", self.stats.grasps_done)
                    return
                self.collect_grasp(grasp_id, object_name)
                progress.note(
                    f"pairs {self.pairs()}, failed draws {self.stats.failed_draws}, skipped {self.stats.skipped}, "
                    f"device retries {self.stats.device_retries}"
                )
                progress.update()
        summary = {
            "stats": dataclasses.asdict(self.stats),
            "wall_s": round(time.monotonic() - self.started, 2),
            "stage_median_ms": {k: round(1e3 * float(np.median(v)), 2) for k, v in self.stage_s.items()},
        }
        summary_file = Path(self.params.out) / "session.json"
        summary_file.write_text(json.dumps(summary, indent=2) + "\n")
        report = check_dataset(self.params.out)
        if not report.ok:
            self.log.error(
                "session ended: %d pairs in %s, but the dataset check FAILED (%d problem(s): %s); counts and stage "
                "times in %s",
                self.pairs(),
                self.params.out,
                len(report.problems),
                "; ".join(report.problems[:5]),
                summary_file,
            )
            raise SystemExit(EXIT_DO_NOT_RESPAWN)
        self.log.info(
            "session complete: %d pairs in %s, dataset check OK; counts and stage times in %s",
            self.pairs(),
            self.params.out,
            summary_file,
        )
        self.request_shutdown()

    def pairs(self) -> int:
        return 0 if self.writer is None else len(self.writer)

    @contextlib.contextmanager
    def stage(self, name: str) -> Iterator[None]:
        started = time.perf_counter()
        yield
        self.stage_s.setdefault(name, []).append(time.perf_counter() - started)

    def sample_id(self, grasp_id: int, finger: str) -> str:
        return f"g{grasp_id:05d}_{finger}"

    def collect_grasp(self, grasp_id: int, object_name: str) -> None:
        attempt = 0
        while attempt < self.params.max_attempts and not self.shutting_down:
            try:
                self.try_grasp(grasp_id, attempt, object_name)
                self.stats.grasps_done += 1
                return
            except GraspFailed as reason:
                self.stats.failed_draws += 1
                self.log.info("grasp %d draw %d: %s", grasp_id, attempt, reason)
                attempt += 1
            except ServiceCallError as error:  # a node died or a device failed: same draw again
                self.stats.device_retries += 1
                self.log.warning("grasp %d: %s; waiting for the node and redoing the grasp", grasp_id, error)
                if error.code == ErrorCode.NOT_REGISTERED:
                    self.registered.pop(object_name, None)
                self.wait_for_nodes()
            finally:  # the release begun while the grasp was written, or one now
                if self.releasing is None:
                    self.release_and_retreat()
                else:
                    self.releasing.result()
                    self.releasing = None
        if not self.shutting_down:
            self.stats.skipped += 1
            self.log.warning("grasp %d on %s skipped after %d draws", grasp_id, object_name, attempt)

    def wait_for_nodes(self) -> None:
        for client in (self.move, self.gripper, self.register, self.patch):
            if not client.wait_for_service(self.params.node_wait_s):
                if self.shutting_down:
                    return  # the graph is stopping with us: nothing to wait for
                raise RuntimeError(f"service {client.name} did not come back in {self.params.node_wait_s} s")
        self.spin_once(0.5)

    def registration(self, object_name: str) -> msgs.RegisterReply:
        if object_name not in self.registered:
            self.wait_for_tactile_and_depth()
            reply = self.register.call(
                msgs.RegisterRequest(object_name=object_name, seed=self.params.seed), timeout_s=60.0, retries=1
            )
            self.log.info(
                "%s registered: fitness %.3f, centroid %s",
                object_name,
                reply.fitness,
                np.round(reply.centroid_world, 3).tolist(),
            )
            self.registered[object_name] = reply
        return self.registered[object_name]

    def wait_for_tactile_and_depth(self) -> None:
        """Spin until both GelSights have published (their backgrounds are needed)."""
        if not self.spin_until(lambda: all(f in self.tactile for f in FINGERS), self.params.node_wait_s):
            raise RuntimeError(f"no tactile images on {self.params.tactile_topics}")

    def draw(self, grasp_id: int, attempt: int, centroid: np.ndarray) -> np.ndarray:
        """(x, y, z of the gel centres, theta_z), seeded by (seed, grasp, attempt).

        The offset is drawn in the gripper's frame: wide along the gels, small along the
        closing axis. A parallel gripper centres what it grasps, so a large offset along the
        closing axis would push the object away from where it was registered."""
        p = self.params
        rng = np.random.default_rng([p.seed, grasp_id, attempt])
        theta = rng.uniform(-np.pi, np.pi)
        along_gel = rng.uniform(-p.offset_xy_m, p.offset_xy_m)
        along_closing = rng.uniform(-p.offset_closing_m, p.offset_closing_m)
        closing_axis = np.array([-np.sin(theta), np.cos(theta)])  # tool y after the turn about world z
        gel_axis = np.array([np.cos(theta), np.sin(theta)])
        x, y = centroid[:2] + along_gel * gel_axis + along_closing * closing_axis
        lowest = p.min_gel_height_m + self.geometry.gel_size_m[1] / 2
        z = max(lowest, centroid[2] + rng.uniform(-p.offset_z_m, p.offset_z_m))
        return np.array([x, y, z, theta])

    def nominal_width_m(
        self, object_name: str, registered: msgs.RegisterReply, x: float, y: float, z: float, theta: float
    ) -> float:
        """The registered model's extent across the fingers at the drawn grasp
        (workcell.kinematics.across_the_gels_m). The gripper is told this width, because a WSG
        detects the part only within its clamping travel around it (the web interface's setting).
        A draw where the model reaches an open gel's face (less ``finger_clearance_m``) is refused:
        coming down, that finger would land on the object."""
        if object_name not in self.model_points:
            mesh = self.scene.mesh(object_name)
            self.model_points[object_name] = sample_model_cloud(mesh, seed=self.params.seed).points_m
        points = transform_points(self.model_points[object_name], registered.model_to_world) - np.array([x, y, z])
        across = across_the_gels_m(points, theta, self.geometry)
        if not across.size:
            raise GraspFailed("the registered model has nothing between the gels at this draw")
        reach_m, open_m = max(across.max(), -across.min()), self.geometry.max_width_m / 2
        if reach_m >= open_m - self.params.finger_clearance_m:
            raise GraspFailed(
                f"a finger would land on the object: it reaches {reach_m * 1e3:.1f} mm across, "
                f"the gels {open_m * 1e3:.1f}"
            )
        return float(across.max() - across.min())

    def try_grasp(self, grasp_id: int, attempt: int, object_name: str) -> None:
        p = self.params
        with self.stage("register"):
            registered = self.registration(object_name)
        x, y, z, theta = self.draw(grasp_id, attempt, registered.centroid_world)
        nominal_width_m = self.nominal_width_m(object_name, registered, x, y, z, theta)
        tcp = grasp_to_tcp_pose(x, y, z + self.geometry.tcp_to_gel_centre_m, theta)
        above = tcp.copy()
        above[2] += p.approach_height_m
        with self.stage("approach"):  # the fingers open on the way to the approach pose
            wide = msgs.GripperCommand(action="move", width_m=self.geometry.max_width_m, speed_m_s=p.gripper_speed_m_s)
            with self.beside(self.gripper.call, wide, timeout_s=p.call_timeout_s) as opening:
                self.arm_to(above)
            opening.result()
            arrived = self.arm_to(tcp)
        with self.stage("close"):
            self.grip_seen_ns = 0
            force_n = self.scene.gripper.grasp_force_n
            grasp = msgs.GripperCommand(
                action="grasp", width_m=nominal_width_m, speed_m_s=p.gripper_speed_m_s, force_n=force_n
            )
            held = self.gripper.call(grasp, timeout_s=p.call_timeout_s)
        if held.state != "holding":
            raise GraspFailed(f"fingers found nothing ({held.state})")
        # Asked for as the fingers hold, the depth-maps are cut while the gels settle.
        gels = gel_poses_world(arrived.tcp_pose, held.width_m, self.geometry)
        request = msgs.PatchRequest(
            object_name=object_name, gel_left_to_world=gels["left"], gel_right_to_world=gels["right"]
        )
        with self.beside(self.patch.call, request, timeout_s=p.call_timeout_s) as cut, self.stage("capture"):
            images = self.capture_at_contact(self.grip_seen())
        with self.stage("depth_maps"):
            try:
                patches = cut.result()
            except ServiceCallError as error:
                if error.code == ErrorCode.OUT_OF_REACH:
                    raise GraspFailed("the registered model is out of the gel's reach") from error
                raise
        # Everything is in hand: the fingers open and the arm lifts while the pairs are written.
        pose = [float(x), float(y), float(z), float(theta)]
        depth_maps = {"left": patches.left, "right": patches.right}
        with self.beside(self.release_and_retreat) as self.releasing, self.stage("write"):
            self.write_grasp(grasp_id, object_name, pose, images, depth_maps, registered.fitness)

    @contextlib.contextmanager
    def beside(self, call: Callable[..., Any], *args: Any, **kwargs: Any) -> Iterator[Future[Any]]:
        """``call`` in the background thread while the block runs, done when it is left (its socket ours again)."""
        running = self.background.submit(call, *args, **kwargs)
        try:
            yield running
        finally:
            wait([running])

    def arm_to(self, tcp_pose: np.ndarray) -> msgs.ArmState:
        self.last_arm = self.move.call(
            msgs.ArmMoveRequest(
                target=tcp_pose, mode="moveL", speed=self.params.arm_speed_m_s, acceleration=self.params.arm_accel_m_s2
            ),
            timeout_s=self.params.call_timeout_s,
        )
        return self.last_arm

    def on_gripper_state(self, state: msgs.GripperState) -> None:
        if state.state == "holding" and not self.grip_seen_ns:
            self.grip_seen_ns = time.time_ns()

    def grip_seen(self) -> int:
        """When ``/gripper/state`` first reported the grip. The GelSights learn of it from that
        stream too (a simulated gel presses only once its node has it), so the settling time
        counts from here, not from the grasp reply, which can come a state period earlier."""
        if not self.spin_until(lambda: self.grip_seen_ns > 0, self.params.call_timeout_s):
            raise ServiceCallError("gripper", ErrorCode.TIMEOUT, "no /gripper/state reporting the grip")
        return self.grip_seen_ns

    def capture_at_contact(self, contact_ns: int) -> dict[str, msgs.TactileImage]:
        """The first frame of each GelSight taken after contact plus the settling time."""
        after = contact_ns + int(self.params.settle_s * 1e9)
        if not self.spin_until(
            lambda: all(f in self.tactile and self.tactile[f].header.stamp_ns > after for f in FINGERS),
            self.params.settle_s + 5.0,
        ):
            raise ServiceCallError("gelsight", ErrorCode.TIMEOUT, "no tactile frame after contact")
        return dict(self.tactile)

    def write_grasp(
        self,
        grasp_id: int,
        object_name: str,
        pose: list[float],
        images: dict[str, msgs.TactileImage],
        depth_maps: dict[str, msgs.DepthMap],
        fitness: float,
    ) -> None:
        """Both fingers' pairs into the dataset in one write (both land or neither), then
        announce them on ``/collector/sample``."""
        if self.writer is None:
            self.writer = self.open_writer(self.new_dataset_info(depth_maps["left"]))
        info = self.writer.info
        size = (info.image_height, info.image_width)
        samples = []
        for finger in FINGERS:
            image, depth_map = images[finger], depth_maps[finger]
            tactile, background = resize_rgb(image.image, *size), resize_rgb(image.background, *size)
            samples.append(
                msgs.DatasetSample(
                    sample_id=self.sample_id(grasp_id, finger),
                    object_name=object_name,
                    grasp_id=grasp_id,
                    finger=finger,
                    grasp_pose=pose,
                    tactile_image=tactile,
                    tactile_diff_image=subtract_background(tactile, background),
                    depth_map_m=depth_map.depth_map_m,
                    depth_range_m=list(info.depth_range_m),
                    registration_fitness=fitness,
                    model_to_gel=depth_map.model_to_gel,
                    gel_to_world=depth_map.gel_to_world,
                    model_to_world=depth_map.model_to_world,
                    depth_crop_m=list(depth_map.crop_m),
                    stamps_ns={"tactile": image.header.stamp_ns, "written": time.time_ns()},
                    scene=info.scene,
                    effects=list(info.effects),
                    split_seed=info.split_seed,
                    depth_map_method=depth_map.method,
                )
            )
        try:
            write_samples(self.writer, samples)
        except DatasetError as error:
            self.fail_on_disk(f"cannot write grasp {grasp_id}: {error}")
        self.stats.pairs_written += len(samples)
        for sample in samples:
            self.samples.publish(sample)

    def new_dataset_info(self, first: msgs.DepthMap) -> DatasetInfo:  # the first pair's map: range, crop, rule
        return DatasetInfo(
            image_height=100,
            image_width=100,
            depth_range_m=(first.y_range_m[0], first.y_range_m[1]),
            scene=self.params.scene,
            effects=tuple(e.name for e in self.scene.effects),
            code_version=code_version(),
            split_seed=self.params.seed,
            depth_crop_m=(first.crop_m[0], first.crop_m[1], first.crop_m[2]),
            depth_map_method=first.method,
        )

    def open_writer(self, info: DatasetInfo | None = None) -> DatasetWriter:
        """The dataset, opened (resumed when ``info`` is None); a disk error ends the session."""
        try:
            return DatasetWriter(self.params.out, info)
        except DatasetError as error:
            self.fail_on_disk(str(error))

    def drop_incomplete_grasps(self, writer: DatasetWriter) -> list[str]:
        """The lone finger samples a torn write left, removed so their grasps are redone whole."""
        try:
            return writer.drop_incomplete_grasps()
        except DatasetError as error:
            self.fail_on_disk(str(error))

    def fail_on_disk(self, reason: str) -> NoReturn:
        """A full disk or an unwritable directory: stop the session; what is written stays."""
        self.log.error("%s — stopping the session; the dataset on disk is intact", reason)
        raise SystemExit(EXIT_DO_NOT_RESPAWN)

    def release_and_retreat(self) -> None:
        """Open the fingers and lift; on the way out of any grasp, failed or not."""
        release = msgs.GripperCommand(
            action="release", width_m=self.geometry.max_width_m, speed_m_s=self.params.gripper_speed_m_s
        )
        with self.stage("release"):
            try:
                self.gripper.call(release, timeout_s=self.params.call_timeout_s)
                if self.last_arm is not None:
                    above = np.array(self.last_arm.tcp_pose, dtype=np.float64)
                    above[2] += self.params.approach_height_m
                    self.arm_to(above)
                    self.last_arm = None  # lifted: a draw refused before the arm moves has nothing to lift
            except ServiceCallError as error:
                self.log.warning("release or retreat failed: %s", error)


if __name__ == "__main__":
    run_node(CollectorNode)
