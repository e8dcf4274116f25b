"""Every backend keeps its kind's device contract: connect / read / disconnect, a context
manager, and DeviceNotConnectedError from one decorator when used unconnected."""

from __future__ import annotations

import importlib
import inspect

import pytest

import drivers.arm
import drivers.depth_camera
import drivers.gelsight
import drivers.gripper
from drivers import BackendEntry, Device, DeviceError, DeviceNotConnectedError, build_backend
from drivers.arm.base import Arm
from drivers.depth_camera.base import DepthCamera
from drivers.gelsight.base import GelSight
from drivers.gripper.base import Gripper

KINDS = [
    (drivers.depth_camera, DepthCamera),
    (drivers.gelsight, GelSight),
    (drivers.gripper, Gripper),
    (drivers.arm, Arm),
]
BACKENDS = [(contract, name, entry) for package, contract in KINDS for name, entry in package.BACKENDS.items()]


@pytest.mark.parametrize(("contract", "name", "entry"), BACKENDS, ids=[f"{c.__name__}-{n}" for c, n, _ in BACKENDS])
def test_each_backend_class_implements_its_kinds_whole_contract(contract: type, name: str, entry: BackendEntry) -> None:
    backend_class = getattr(importlib.import_module(entry.module), entry.backend_class)
    assert issubclass(backend_class, contract) and issubclass(contract, Device)
    assert issubclass(contract.NOT_CONNECTED, DeviceNotConnectedError) and contract.NOT_CONNECTED is not (
        DeviceNotConnectedError
    )  # also the kind's own error, which the kind's node catches
    assert not inspect.isabstract(backend_class), backend_class.__abstractmethods__


SIMULATED = {
    "depth camera": lambda: drivers.depth_camera.make_backend({"backend": "simulated", "camera": "left"}),
    "gelsight": lambda: drivers.gelsight.make_backend({"backend": "simulated"}),
    "arm": lambda: drivers.arm.make_backend({"backend": "simulated", "scene": "scenes/ideal.yaml", "time_scale": 0.0}),
}


@pytest.mark.parametrize("kind", sorted(SIMULATED))
def test_a_simulated_backend_refuses_to_read_unconnected_and_connects_as_a_context_manager(kind: str) -> None:
    backend = SIMULATED[kind]()
    assert not backend.is_connected
    with pytest.raises(DeviceNotConnectedError, match=r"\.read: the device is not connected; call connect\(\) first"):
        backend.read()
    with backend as connected:
        assert connected is backend and backend.is_connected
        assert backend.read().header.stamp_ns > 0
    assert not backend.is_connected
    with pytest.raises(DeviceError):
        backend.read()


def test_a_backend_that_breaks_its_contract_is_refused_when_built() -> None:
    entry = BackendEntry("drivers.depth_camera.simulated", "SimulatedDepthCamera", "SimulatedDepthCameraConfig")
    with pytest.raises(TypeError, match="does not keep the Gripper contract"):
        build_backend(Gripper, "gripper", {"backend": "fake", "camera": "left"}, {"fake": entry})
