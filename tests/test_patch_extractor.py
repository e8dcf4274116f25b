"""The patch extractor's refusals carry codes the collector branches on, not sentences."""

from __future__ import annotations

import threading

import numpy as np
import pytest

import msgs
from bus.pubsub import Bus
from bus.registry import Registry
from bus.services import ServiceCallError
from msgs.system import ErrorCode
from nodes.patch_extractor import GelOutOfReach, PatchExtractorNode, Registered
from perception.pointcloud import VoxelIndex


def _gel_at(x_m: float) -> np.ndarray:
    gel_to_world = np.eye(4)
    gel_to_world[0, 3] = x_m
    return gel_to_world


def test_a_patch_of_an_unregistered_object_is_refused_with_its_code(registry: Registry) -> None:
    node = PatchExtractorNode("patch_extractor", {}, registry=registry)
    stop = threading.Event()
    spinner = threading.Thread(target=node.spin, kwargs={"until": stop.is_set}, daemon=True)
    spinner.start()
    caller = Bus("caller", registry)
    try:
        patch = caller.client("/perception/patch", msgs.PatchRequest, msgs.PatchReply)
        with pytest.raises(ServiceCallError) as refused:
            patch.call(
                msgs.PatchRequest(
                    object_name="mustard_bottle", gel_left_to_world=_gel_at(0.0), gel_right_to_world=_gel_at(0.05)
                ),
                timeout_s=10.0,
                retries=0,
            )
        assert refused.value.code == ErrorCode.NOT_REGISTERED
        assert "mustard_bottle" in refused.value.text
    finally:
        stop.set()
        spinner.join(10.0)
        caller.close()
        node.close()


def test_a_gel_that_reaches_nothing_is_refused_as_out_of_reach(registry: Registry) -> None:
    node = PatchExtractorNode("patch_extractor", {}, registry=registry)
    try:
        cube_m = np.random.default_rng(0).uniform(-0.01, 0.01, (2000, 3))
        node.registered["mustard_bottle"] = Registered(VoxelIndex(cube_m), np.eye(4))
        far = msgs.PatchRequest(
            object_name="mustard_bottle", gel_left_to_world=_gel_at(1.0), gel_right_to_world=_gel_at(1.05)
        )
        with pytest.raises(GelOutOfReach) as refused:
            node.on_patch(far)
        assert refused.value.code == ErrorCode.OUT_OF_REACH
    finally:
        node.close()
