"""Patch extractor node: turns the depth cameras' frames into what Algorithm 1 needs.

- ``/perception/register`` (RegisterRequest -> RegisterReply): segment the named object in
  the latest frame of every camera (merged in ``world``), register its complete model cloud
  (FPFH + RANSAC, then point-to-plane ICP) and keep the pose.
- ``/perception/patch`` (PatchRequest -> PatchReply): both fingers' contact depth-maps of
  the registered model cloud for the given gel poses, the model first placed where the grasp
  holds it between the gels, each pressed as the scene's grasp force needs
  (perception.gripper_centring; a grasp pushes a free-standing object there;
  ``centre_between_gels: false`` for an object that cannot move).
- Publishes what it extracted (``/perception/object_cloud``, ``/perception/depth_map``, and
  the registered pose as the ``world -> object`` transform on ``/perception/object_pose``) so a
  session bag holds it, and the depth frames each registration used
  (``/perception/registration_frames``, one per camera): from them and the session's touches
  ``dtx calibrate touches`` corrects the cameras' extrinsics, and ``dtx dataset redepth
  --calibration`` registers again with the corrected ones.

Params: ``scene`` (which objects exist, their meshes and nominal places, the gripper
geometry — for the lab, a scene file describing the real table), ``cameras`` (depth topics),
``depth_map_rows``/``depth_map_cols``, ``margin_m``, ``depth_map_method`` (what a bin holds:
``surface`` or ``nearest_point``, perception.surface), ``seed``.
"""

from __future__ import annotations

import dataclasses
import functools
import time
from concurrent.futures import Future
from typing import Any

import numpy as np

import msgs
from bus.node import Node, run_node
from msgs.system import ErrorCode
from nodes.transforms import frame_transform
from perception.depthmap import (
    MODEL_CLOUD_SEED,
    MODEL_POINT_SPACING_M,
    DepthMapParams,
    contact_depth_map,
    crop_reach_m,
)
from perception.errors import OutOfReachError
from perception.gripper_centring import centre_between_gels
from perception.pointcloud import VoxelIndex, depth_images_to_world, transform_points
from perception.registration import PreparedModel, prepare_model, register_model, sample_model_cloud
from perception.segmentation import segment_object, segmentation_params_for
from workcell.scene import load_scene


@dataclasses.dataclass
class Registered:
    model: VoxelIndex  # the dense depth-map cloud, in the model frame
    model_to_world: np.ndarray


class NotRegistered(ValueError):
    """A patch asked for an object with no registered pose: the caller registers it again."""

    code = ErrorCode.NOT_REGISTERED


class GelOutOfReach(ValueError):
    """A gel reaches no point of the registered model: that grasp cannot give a patch."""

    code = ErrorCode.OUT_OF_REACH


class PatchExtractorNode(Node):
    @dataclasses.dataclass
    class Params:
        scene: str = "scenes/ycb_three.yaml"
        cameras: list = dataclasses.field(default_factory=lambda: ["/camera_left/depth", "/camera_right/depth"])
        depth_map_rows: int = 100
        depth_map_cols: int = 100
        # The crop is larger than the sensed area, as the paper's: a calibration residual of a
        # mm or two must stay inside it for the learner to absorb.
        margin_m: float = 0.002
        y_range_m: list = dataclasses.field(default_factory=lambda: [-0.005, 0.010])
        fill_gaps_min_neighbours: int = DepthMapParams.fill_gaps_min_neighbours
        # What a bin holds (perception.surface.DEPTH_MAP_METHODS): "surface", the object's surface
        # at the bin centre; "nearest_point", the paper's nearest point. Each DepthMap says which.
        depth_map_method: str = "surface"
        centre_between_gels: bool = True
        seed: int = 0

    def __init__(self, name: str, params: dict[str, Any] | None = None, **kwargs: Any) -> None:
        super().__init__(name, params, **kwargs)
        self.scene = load_scene(self.params.scene)
        self.geometry = self.scene.gripper_geometry()
        self.depth_map_params = DepthMapParams(
            shape=(self.params.depth_map_rows, self.params.depth_map_cols),
            margin_m=self.params.margin_m,
            y_range_m=(self.params.y_range_m[0], self.params.y_range_m[1]),
            fill_gaps_min_neighbours=self.params.fill_gaps_min_neighbours,
            method=self.params.depth_map_method,
        )
        self.reach_m = crop_reach_m(self.geometry, self.depth_map_params)
        self.latest: dict[str, msgs.DepthImage] = {}
        for topic in self.params.cameras:
            self.create_subscription(topic, msgs.DepthImage, functools.partial(self.latest.__setitem__, topic))
        self.models: dict[str, tuple[VoxelIndex, PreparedModel]] = {}
        self.registered: dict[str, Registered] = {}
        self.cloud = self.create_publisher("/perception/object_cloud", msgs.PointCloud, latched=True)
        self.depth_maps = self.create_publisher("/perception/depth_map", msgs.DepthMap)
        # world -> object of the last registration, for the transform tree (bags, Foxglove)
        self.object_pose = self.create_publisher("/perception/object_pose", msgs.FrameTransform, latched=True)
        self.registration_frames = self.create_publisher("/perception/registration_frames", msgs.DepthImage)
        self.create_service("/perception/register", msgs.RegisterRequest, msgs.RegisterReply, self.on_register)
        self.create_service("/perception/patch", msgs.PatchRequest, msgs.PatchReply, self.on_patch)

    def on_register(self, request: msgs.RegisterRequest) -> Future[msgs.RegisterReply]:
        objects = {o.name: o for o in self.scene.objects if o.mesh}
        if request.object_name not in objects:
            raise ValueError(f"object {request.object_name!r} unknown; this scene has {sorted(objects)}")
        return self.background.submit(self._register, objects[request.object_name], request.seed)

    def latest_frames(self, timeout_s: float = 30.0) -> list[msgs.DepthImage]:
        """The newest frame of every camera, waiting for cameras that are still starting."""
        deadline = time.monotonic() + timeout_s
        while missing := [t for t in self.params.cameras if t not in self.latest]:
            if time.monotonic() > deadline or self.shutting_down:  # the node's close waits for this thread
                raise RuntimeError(f"no depth frame from {missing} in {timeout_s} s")
            time.sleep(0.05)
        return [self.latest[t] for t in self.params.cameras]

    def _register(self, spec: Any, seed: int) -> msgs.RegisterReply:
        frames = self.latest_frames()
        if spec.name not in self.models:
            # Registration works on a 2 mm cloud; a depth-map needs a far denser one.
            dense_points = sample_model_cloud(spec.mesh, MODEL_POINT_SPACING_M, seed=MODEL_CLOUD_SEED).points_m
            self.models[spec.name] = (
                VoxelIndex(dense_points),
                prepare_model(sample_model_cloud(spec.mesh, seed=self.params.seed)),
            )
        dense, prepared = self.models[spec.name]
        segmented = segment_object(
            depth_images_to_world(frames),
            segmentation_params_for(self.scene),
            hint_world_m=np.array([spec.x_m, spec.y_m, 0.0]),
            seed=seed,
        )
        result = register_model(prepared, segmented.points_world_m, seed=seed)
        self.registered[spec.name] = Registered(dense, result.model_to_world)
        for frame in frames:
            self.registration_frames.publish(frame)
        self.cloud.publish(
            msgs.PointCloud(header=msgs.Header(frame_id="world"), points=segmented.points_world_m.astype(np.float32))
        )
        self.object_pose.publish(frame_transform("world", "object", result.model_to_world, time.time_ns()))
        self.log.info(
            "registered %s: fitness %.3f, rmse %.2f mm, %d points",
            spec.name,
            result.fitness,
            result.inlier_rmse_m * 1e3,
            len(segmented.points_world_m),
        )
        return msgs.RegisterReply(
            header=msgs.Header(frame_id="world"),
            object_name=spec.name,
            model_to_world=result.model_to_world,
            fitness=result.fitness,
            inlier_rmse_m=result.inlier_rmse_m,
            centroid_world=segmented.centroid_world_m,
            point_counts=segmented.point_counts,
        )

    def on_patch(self, request: msgs.PatchRequest) -> msgs.PatchReply:
        registered = self.registered.get(request.object_name)
        if registered is None:
            raise NotRegistered(f"object {request.object_name!r} is not registered; call /perception/register first")
        gels = {"left": request.gel_left_to_world, "right": request.gel_right_to_world}
        model_to_world = registered.model_to_world
        near = {
            finger: registered.model.within(
                transform_points(gel[:3, 3][None], np.linalg.inv(model_to_world))[0], self.reach_m
            )
            for finger, gel in gels.items()
        }
        if self.params.centre_between_gels:
            gripper = self.scene.gripper
            model_to_world = centre_between_gels(
                np.concatenate(list(near.values())),
                model_to_world,
                gels["left"],
                gels["right"],
                self.geometry,
                gripper.grasp_force_n,
                gripper.foundation_stiffness_n_per_mm3,
            )
        maps = {}
        for finger, gel_to_world in gels.items():
            try:
                patch = contact_depth_map(
                    near[finger], model_to_world, gel_to_world, self.geometry, self.depth_map_params
                )
            except OutOfReachError as err:
                raise GelOutOfReach(f"{finger} gel: {err}") from err
            maps[finger] = msgs.DepthMap(
                header=msgs.Header(frame_id=f"gel_{finger}"),
                depth_map_m=patch.depth_map_m,
                finger=finger,
                crop_m=list(patch.crop_m),
                y_range_m=list(patch.y_range_m),
                point_count=patch.point_count,
                model_to_gel=np.linalg.inv(gel_to_world) @ model_to_world,
                gel_to_world=gel_to_world,
                model_to_world=registered.model_to_world,
                method=self.depth_map_params.method,
            )
            self.depth_maps.publish(maps[finger])
        return msgs.PatchReply(left=maps["left"], right=maps["right"])


if __name__ == "__main__":
    run_node(PatchExtractorNode)
