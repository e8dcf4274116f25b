"""Typed, versioned messages of the dtx bus and their wire codec (no pickle anywhere)."""

from msgs.base import MESSAGE_TYPES, Header, Message
from msgs.dataset import DatasetSample
from msgs.inference import TactileEstimateReply, TactileEstimateRequest
from msgs.perception import DepthMap, PatchReply, PatchRequest, RegisterReply, RegisterRequest
from msgs.robot import ArmMoveRequest, ArmState, GraspCommand, GripperCommand, GripperState
from msgs.sensors import CameraIntrinsics, DepthImage, PointCloud, TactileImage
from msgs.system import Clock, Empty, ErrorCode, FrameTransform, Heartbeat, Log, ServiceError

__all__ = [
    "MESSAGE_TYPES",
    "Header",
    "Message",
    "DatasetSample",
    "TactileEstimateReply",
    "TactileEstimateRequest",
    "DepthMap",
    "PatchReply",
    "PatchRequest",
    "RegisterReply",
    "RegisterRequest",
    "ArmMoveRequest",
    "ArmState",
    "GraspCommand",
    "GripperCommand",
    "GripperState",
    "CameraIntrinsics",
    "DepthImage",
    "PointCloud",
    "TactileImage",
    "Clock",
    "Empty",
    "ErrorCode",
    "FrameTransform",
    "Heartbeat",
    "Log",
    "ServiceError",
]
