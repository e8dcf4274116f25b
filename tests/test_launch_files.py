"""The shipped launch files: the lab's runs Algorithm 1 with the same nodes as the simulated
session, and each pipeline node's parameters are ones it accepts and that name the graph's own
topics. (A device node's parameters go to its backend: tests/test_drivers_hw_check.py.)"""

from __future__ import annotations

import importlib
from pathlib import Path
from typing import Any

import pytest

from bus.node import Node, parse_params
from dtx.launch import LaunchDescription, load_launch

LAUNCH = Path(__file__).resolve().parent.parent / "launch"
# Everything a session needs beyond its devices.
PIPELINE = {
    "patch_extractor": "nodes.patch_extractor",
    "collector": "nodes.collector",
    "transforms": "nodes.transforms",
    "recorder": "nodes.recorder",
}


def node_params(module: str, name: str, values: dict[str, Any]) -> Any:
    """The node's parameter dataclass built from ``values`` as the node itself builds it."""
    namespace = vars(importlib.import_module(module))
    [node_class] = [
        c
        for c in namespace.values()
        if isinstance(c, type) and issubclass(c, Node) and c.__module__ == module and hasattr(c, "Params")
    ]
    return parse_params(node_class.Params, values, name)


def load(path: str) -> LaunchDescription:
    return load_launch(LAUNCH / path, {"robot_ip": "192.0.2.10"} if path == "collect_lab.yaml" else {})


@pytest.mark.parametrize("path", ["collect_sim.yaml", "collect_lab.yaml"])
def test_a_collection_launch_runs_the_whole_pipeline_on_its_own_cameras(path: str) -> None:
    nodes = {spec.name: spec for spec in load(path).nodes}
    assert {name: nodes[name].module for name in PIPELINE if name in nodes} == PIPELINE
    params = {name: node_params(module, name, nodes[name].params) for name, module in PIPELINE.items()}
    cameras = sorted(name for name, spec in nodes.items() if spec.module == "nodes.depth_camera")
    assert len(cameras) == 2
    assert sorted(params["patch_extractor"].cameras) == [f"/{camera}/depth" for camera in cameras]
    assert sorted(params["transforms"].cameras) == cameras
    assert nodes["collector"].required
    assert params["collector"].scene == params["patch_extractor"].scene == params["transforms"].scene


def test_the_lab_session_takes_the_simulated_sessions_arguments() -> None:
    assert set(load("collect_sim.yaml").args) <= set(load("collect_lab.yaml").args)
