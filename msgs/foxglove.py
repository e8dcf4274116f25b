"""Foxglove's well-known message for each dtx message that has one (images, clouds,
transforms): bags carry them beside the dtx encoding and the live bridge serves them, so
Foxglove Studio shows a session without any plug-in."""

from __future__ import annotations

from typing import Any

import foxglove.messages as fox
import numpy as np

import msgs
from msgs.base import Message


def _foxglove_time(stamp_ns: int) -> fox.Timestamp:
    return fox.Timestamp(sec=stamp_ns // 1_000_000_000, nsec=stamp_ns % 1_000_000_000)


# Where a dtx topic's Foxglove form goes, in bags and live alike: one name for both.
FOXGLOVE_SUFFIX = "/foxglove"


def foxglove_schema(dtx_schema: str) -> Any | None:
    """The Foxglove schema of a dtx schema's view (None: it has none), known before any
    message comes, so a channel can be advertised as soon as its topic is discovered."""
    view = {
        msgs.DepthImage.SCHEMA: fox.RawImage,
        msgs.TactileImage.SCHEMA: fox.RawImage,
        msgs.DatasetSample.SCHEMA: fox.RawImage,
        msgs.PointCloud.SCHEMA: fox.PointCloud,
        msgs.FrameTransform.SCHEMA: fox.FrameTransform,
    }.get(dtx_schema)
    return view().get_schema() if view is not None else None


def foxglove_frames(message: Message) -> tuple[str, str]:
    """The frames ``message``'s Foxglove view is drawn in: (frame id, child frame id), the child
    "" but for a transform. Messages of one topic with other frames show other things (each
    finger's sample, each transform of the tree), so the live bridge limits each pair apart."""
    if isinstance(message, msgs.DatasetSample):
        # A sample's contact depth-map is drawn in the gel frame of its finger.
        return f"gel_{message.finger}", ""
    if isinstance(message, msgs.FrameTransform):
        return message.header.frame_id, message.child_frame_id
    return message.header.frame_id, ""


def _raw_image(stamp_ns: int, frame_id: str, pixels: np.ndarray, encoding: str) -> fox.RawImage:
    """A RawImage of C-contiguous ``pixels`` (rows first), in Foxglove's ``encoding``."""
    return fox.RawImage(
        timestamp=_foxglove_time(stamp_ns),
        frame_id=frame_id,
        width=pixels.shape[1],
        height=pixels.shape[0],
        encoding=encoding,
        step=pixels.strides[0],
        data=pixels.tobytes(),
    )


def foxglove_view(message: Message) -> Any | None:
    """The Foxglove well-known message showing ``message``, or None if it has none."""
    header = message.header
    if isinstance(message, msgs.DepthImage):
        depth = np.ascontiguousarray(message.depth)
        encoding = "16UC1" if depth.dtype == np.uint16 else "32FC1"
        return _raw_image(header.stamp_ns, header.frame_id, depth, encoding)
    if isinstance(message, msgs.TactileImage):
        return _raw_image(header.stamp_ns, header.frame_id, np.ascontiguousarray(message.image), "rgb8")
    if isinstance(message, msgs.DatasetSample):
        # The sample's contact depth-map: 32FC1, metres along the gel's outward normal (bins with
        # no surface hold the far end of the depth range).
        depth_map = np.ascontiguousarray(message.depth_map_m, dtype=np.float32)
        return _raw_image(header.stamp_ns, foxglove_frames(message)[0], depth_map, "32FC1")
    if isinstance(message, msgs.PointCloud):
        points = np.ascontiguousarray(message.points, dtype=np.float32)
        fields = [
            fox.PackedElementField(name=axis, offset=4 * i, type=fox.PackedElementFieldNumericType.Float32)
            for i, axis in enumerate("xyz")
        ]
        return fox.PointCloud(
            timestamp=_foxglove_time(header.stamp_ns),
            frame_id=header.frame_id,
            point_stride=12,
            fields=fields,
            data=points.tobytes(),
        )
    if isinstance(message, msgs.FrameTransform):
        t, q = message.translation, message.rotation
        return fox.FrameTransform(
            timestamp=_foxglove_time(header.stamp_ns),
            parent_frame_id=header.frame_id,
            child_frame_id=message.child_frame_id,
            translation=fox.Vector3(x=float(t[0]), y=float(t[1]), z=float(t[2])),
            rotation=fox.Quaternion(x=float(q[0]), y=float(q[1]), z=float(q[2]), w=float(q[3])),
        )
    return None
