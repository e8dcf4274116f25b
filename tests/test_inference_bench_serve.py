"""``dtx bench serve`` runs the real node in its own process and reports its figures."""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np
import pytest
import torch

from benchmarks.serve import add_arguments, run
from models.runtime import cuda_missing
from perception.surface import DEPTH_MAP_METHODS


def test_serve_benchmark_reports_latency_and_throughput_of_the_named_weights() -> None:
    parser = argparse.ArgumentParser()
    add_arguments(parser)
    result = run(
        parser.parse_args(["--width", "8", "--threads", "1", "--requests", "5", "--regions", "4", "--seconds", "0.3"])
    )
    assert result["weights"] == "fresh generator, width 8 (seeded, untrained)"
    assert result["model"] == "fresh.pt (ngf 8, onnxrt fp32, cpu) serves the network (its uncertainty absent)"
    assert 0 < result["p50_ms"] <= result["p99_ms"]
    assert result["regions_per_s"] > 0 and result["server_cpu_ms_per_region"] > 0
    assert result["thread_split"] == {"lanes": 1, "lane_threads": 1, "input_threads": 1, "input_in_lanes": True}


def test_serve_benchmark_reports_the_priors_share_and_the_cloud_form() -> None:
    """--prior serves a generator correcting the physics prior and says what the prior costs;
    --points sends a YCB model cloud with gel poses on its surface beside the depth-map form."""
    parser = argparse.ArgumentParser()
    add_arguments(parser)
    served = "--width 8 --threads 1 --requests 3 --regions 2 --seconds 0.2 --prior"
    asked = "--points --objects 1 --poses 4 --point-requests 1"
    result = run(parser.parse_args(f"{served} {asked}".split()))
    assert result["weights"] == "fresh generator, width 8, physics prior (seeded, untrained)"
    assert 0 < result["prior_cpu_ms_per_region"] and 0 < result["prior_share_of_server_cpu"]
    assert result["thread_split"] == {"lanes": 1, "lane_threads": 1, "input_threads": 1, "input_in_lanes": True}
    (row,) = result["points"]
    assert row["poses"] == 4 and row["cloud_points"] > 1_000_000
    for key in (
        "cut_regions_per_s",
        "cut_per_gel_regions_per_s",
        "handle_regions_per_s",
        "points_regions_per_s",
        "maps_regions_per_s",
        "network_regions_per_s",
    ):
        assert row[key] > 0
    assert row["handle_server_cpu_ms_per_region"] >= 0  # counted in clock ticks: 4 tiny regions may take none
    # The stages measured alone on the row's regions (the cut by each bin rule too, issue 50), and
    # the targets as ratios of the same run.
    assert set(row["stage_cpu_ms_per_region"]) == {
        "cut_cpu_ms",
        *(f"cut_{method}_cpu_ms" for method in DEPTH_MAP_METHODS),
        "prior_cpu_ms",
        "network_cpu_ms",
        "encode_cpu_ms",
        "network_regions_per_s",
        "network_one_pass_cpu_ms",
        "network_one_pass_regions_per_s",
    }
    assert all(value > 0 for value in row["stage_cpu_ms_per_region"].values())
    assert row["handle_over_network"] == round(row["handle_regions_per_s"] / row["network_regions_per_s"], 3)
    assert row["handle_over_maps"] == round(row["handle_regions_per_s"] / row["maps_regions_per_s"], 3)
    stages = row["stage_cpu_ms_per_region"]
    one_pass = stages["network_one_pass_regions_per_s"]
    assert row["handle_over_one_pass_network"] == round(row["handle_regions_per_s"] / one_pass, 3)
    for network, ratio in (
        ("network_cpu_ms", "server_cpu_over_network"),
        ("network_one_pass_cpu_ms", "server_cpu_over_one_pass_network"),
    ):
        assert row[ratio] == round(row["handle_server_cpu_ms_per_region"] / stages[network], 3)


def test_serve_benchmark_sets_a_checkpoints_forms_side_by_side(tmp_path: Path) -> None:
    """--forms serves one checkpoint as trained before the uncertainty (its network alone), as
    its network with the uncertainty, and as it says (here the prior), each through the node in
    the same run; the served prior runs no network and its stages say what the uncertainty costs."""
    from benchmarks.serve import write_checkpoint
    from models.uncertainty import Calibration, ServedUncertainty, UncertaintyConfig, UncertaintyNet

    checkpoint = write_checkpoint(tmp_path / "fitted.pt", width=8, prior=True)
    state = torch.load(checkpoint, weights_only=True)
    uncertainty = ServedUncertainty(UncertaintyNet(4, 4), Calibration((1.0,), (1.0,)), UncertaintyConfig(width=4))
    torch.save({**state, "serves": "prior", "uncertainty": uncertainty.to_state()}, checkpoint)
    parser = argparse.ArgumentParser()
    add_arguments(parser)
    served = f"--checkpoint {checkpoint} --threads 1 --requests 2 --regions 2 --seconds 0.2"
    asked = "--points --objects 1 --poses 4 --point-requests 1 --forms before network served"
    result = run(parser.parse_args(f"{served} {asked}".split()))
    table = result["side_by_side"]
    assert list(table) == ["before", "network", "served"]
    assert table["before"]["model"] == "before.pt (ngf 8, onnxrt fp32, cpu) serves the network (its uncertainty absent)"
    assert table["network"]["model"] == "fitted.pt (ngf 8, onnxrt fp32, cpu) serves the network"
    assert table["served"]["model"] == "fitted.pt (ngf 8, cpu) serves the prior: no network pass"
    assert table["before"]["handle_over_before"] == 1.0 and table["served"]["handle_over_before"] > 0
    (row,) = result["forms"]["served"]["points"]
    assert row["stage_cpu_ms_per_region"]["uncertainty_cpu_ms"] > 0
    (row,) = result["forms"]["before"]["points"]
    assert "uncertainty_cpu_ms" not in row["stage_cpu_ms_per_region"]


@pytest.mark.skipif(not cuda_missing("onnxrt"), reason="this machine's ONNX Runtime has CUDA")
def test_serve_benchmark_on_cuda_without_it_stops_with_the_code_before_starting_a_node() -> None:
    parser = argparse.ArgumentParser()
    add_arguments(parser)
    with pytest.raises(SystemExit, match="dtx bench serve: cuda_unavailable: device 'cuda' was asked for"):
        run(parser.parse_args(["--width", "8", "--device", "cuda"]))


@pytest.mark.parametrize("method", ["surface", "nearest_point"])
def test_surface_gel_poses_are_rigid_and_touch_the_model(method: str) -> None:
    """Every pose is a rigid gel frame whose +y faces the surface 0.5 mm in: its depth-map
    reaches into the gel (a scanned mesh is not flat, so some points lie deeper), at most 0.5 mm
    where it sits, the map's centre, by either rule of what a bin holds."""
    from benchmarks.serve import YCB, surface_gel_poses
    from perception.depthmap import DepthMapParams, contact_depth_maps
    from perception.pointcloud import VoxelIndex, check_transform
    from perception.registration import sample_model_cloud
    from workcell.kinematics import GripperGeometry

    cloud = sample_model_cloud(YCB[1], 0.0003, seed=0)
    poses = surface_gel_poses(cloud, 8, seed=1)
    for pose in poses:
        check_transform(pose)
    maps = contact_depth_maps(
        VoxelIndex(cloud.points_m),
        np.eye(4),
        poses,
        GripperGeometry(),
        DepthMapParams(fill_gaps_min_neighbours=0, method=method),
    ).depth_maps_m
    assert np.all(maps.min(axis=(1, 2)) <= -0.0004)
    np.testing.assert_allclose(maps[:, 49:51, 49:51].min(axis=(1, 2)), -0.0005, atol=2e-4)
