"""How much each sweep measures: the full report and the reduced quick one (every table at
lower counts, <= 30 min on 2 cores). The report lists every field where the two differ, so what
--quick left out is stated from these values, never written by hand."""

from __future__ import annotations

import dataclasses

# The sweeps in the order they run (report.sweeps.SWEEPS), named here so that the command
# line can list them without importing torch and Open3D.
SWEEP_NAMES = (
    "resolution",
    "training_length",
    "width",
    "density",
    "depth_map",
    "pose_sigma",
    "gelsight_effects",
    "uncertainty",
    "serving",
    "inference",
    "registration",
    "depth_effects",
    "calibration_grasps",
    "pipeline",
)


@dataclasses.dataclass(frozen=True)
class Plan:
    name: str
    samples: int  # analytic contacts (two per grasp), split 70/15/15
    session_grasps: int  # grasps collected on the simulated scene (two pairs each)
    library_samples: int  # contact-library pairs trained beside the session (as the default model)
    epochs: int  # constant-rate epochs of every training (then as many decaying)
    densities: tuple[float, ...]  # points/cm³ (paper Table II)
    resolutions: tuple[int, ...]  # depth-map bins per side
    depth_map_methods: tuple[str, ...]  # what a bin holds (perception.surface.DEPTH_MAP_METHODS)
    pose_sigmas_mm: tuple[float, ...]  # in-plane pose errors the session model is served with (mm)
    registration_poses: int  # poses per YCB mesh in the registration sweeps
    voxel_mm: tuple[int, ...]
    ransac_iterations: tuple[int, ...]
    icp_distances_mm: tuple[tuple[int, ...], ...]
    depth_effects_alone: bool  # also each depth effect on its own, not just none/all
    depth_frames: int  # frames timed per depth-effect setting
    trained_widths: tuple[int, ...]  # generators trained to compare their SSIM against the truth
    widths: tuple[int, ...]  # generators (random weights) in the runtime benchmark
    precisions: tuple[str, ...]
    runtimes: tuple[str, ...]
    inference_seconds: float  # measuring time per inference figure
    dropout_samples: tuple[int, ...]
    calibration_grasps: tuple[int, ...]  # session training grasps the cameras are calibrated from
    seed: int = 0

    def reductions(self, reference: "Plan") -> list[str]:
        """'field: ours (reference theirs)' for every field that differs."""
        return [
            f"{f.name}: {getattr(self, f.name)} (full: {getattr(reference, f.name)})"
            for f in dataclasses.fields(self)
            if f.name != "name" and getattr(self, f.name) != getattr(reference, f.name)
        ]


FULL = Plan(
    name="full",
    samples=578,
    session_grasps=289,
    library_samples=600,
    epochs=5,
    densities=(1.0, 10.0, 20.0, 40.0, 80.0),
    resolutions=(50, 100, 200),
    depth_map_methods=("surface", "nearest_point"),
    pose_sigmas_mm=(0.0, 0.5, 1.0, 1.5, 2.0, 3.0),
    registration_poses=3,
    voxel_mm=(2, 4, 6, 8, 10),
    ransac_iterations=(1_000, 5_000, 20_000, 100_000),
    icp_distances_mm=((4,), (8,), (16,), (16, 8), (16, 4)),
    depth_effects_alone=True,
    depth_frames=20,
    trained_widths=(16, 32, 64),
    widths=(16, 32, 64),
    precisions=("fp32", "bf16", "int8"),
    runtimes=("eager", "onnxrt"),
    inference_seconds=1.5,
    dropout_samples=(2, 4, 8, 16),
    calibration_grasps=(10, 30, 100, 300, 1000),
)

QUICK = dataclasses.replace(
    FULL,
    name="quick",
    samples=120,
    session_grasps=40,
    library_samples=60,
    epochs=2,
    registration_poses=1,
    voxel_mm=(4, 8),
    ransac_iterations=(1_000, 20_000),
    icp_distances_mm=((8,), (16, 8)),
    depth_effects_alone=False,
    depth_frames=5,
    trained_widths=(16, 32),
    inference_seconds=0.3,
    dropout_samples=(2, 4, 8),
    calibration_grasps=(30,),
)
