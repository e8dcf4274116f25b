"""What a dataset states about itself and its samples: ``dataset.json`` and the manifest.

Layout of a dataset directory ``DIR``::

    DIR/dataset.json          format name + version, image size, depth_range_m, scene,
                              effects, code version, split seed (written once)
    DIR/manifest.jsonl        one JSON object per sample, appended after its files exist
    DIR/tactile/<id>.png      GelSight image, RGB, as captured (viewable)
    DIR/tactile_diff/<id>.png background-subtracted copy: image - background + 128, RGB
    DIR/depth/<id>.npy        contact depth-map, float32 metres in the gel frame
                              (min y per bin; NaN or +inf = empty bin), np.save format

``dataset.writer`` lands samples in it, ``dataset.reader`` reads them back.
"""

from __future__ import annotations

import dataclasses
import re
from pathlib import Path
from typing import Any

import numpy as np

from perception.surface import DEPTH_MAP_METHODS

FORMAT_NAME = "dtx-tactile-dataset"
FORMAT_VERSION = 1
FINGERS = ("left", "right")
FILE_KINDS = ("tactile", "tactile_diff", "depth")
_FILE_SUFFIX = {"tactile": ".png", "tactile_diff": ".png", "depth": ".npy"}
SAMPLE_ID = re.compile(r"^[A-Za-z0-9][A-Za-z0-9_.-]{0,127}$")
# Readers trust no file: an image size is bounded before anything is allocated for it.
MAX_IMAGE_SIDE = 4096


class DatasetError(ValueError):
    """The dataset on disk, or a sample given to it, is not what the format requires."""


@dataclasses.dataclass(frozen=True)
class DatasetInfo:
    """Dataset-wide facts, stored once in ``dataset.json``."""

    image_height: int = 100
    image_width: int = 100
    depth_range_m: tuple[float, float] = (-0.002, 0.003)
    scene: str = ""
    effects: tuple[str, ...] = ()
    code_version: str = ""
    split_seed: int = 0
    # The depth-maps' crop volume (x, y, z extent in the gel frame, m); None where unknown
    # (datasets not made from a model, e.g. the synthetic ones).
    depth_crop_m: tuple[float, float, float] | None = None
    # What a depth-map bin holds (perception.surface.DEPTH_MAP_METHODS): a dataset written before
    # the surface rule names none, and its maps are the paper's nearest points.
    depth_map_method: str = "nearest_point"

    def to_json(self) -> dict[str, Any]:
        data = {
            "format": FORMAT_NAME,
            "version": FORMAT_VERSION,
            "image_height": self.image_height,
            "image_width": self.image_width,
            "depth_range_m": list(self.depth_range_m),
            "scene": self.scene,
            "effects": list(self.effects),
            "code_version": self.code_version,
            "split_seed": self.split_seed,
            "depth_map_method": self.depth_map_method,
        }
        if self.depth_crop_m is not None:
            data["depth_crop_m"] = list(self.depth_crop_m)
        return data

    @staticmethod
    def from_json(data: dict[str, Any]) -> "DatasetInfo":
        if data.get("format") != FORMAT_NAME:
            raise DatasetError(f"dataset.json: format is {data.get('format')!r}, expected {FORMAT_NAME!r}")
        if data.get("version") != FORMAT_VERSION:
            raise DatasetError(
                f"dataset.json: version {data.get('version')!r} is not supported "
                f"(this code reads version {FORMAT_VERSION})"
            )
        try:
            info = DatasetInfo(
                image_height=int(data["image_height"]),
                image_width=int(data["image_width"]),
                depth_range_m=(float(data["depth_range_m"][0]), float(data["depth_range_m"][1])),
                scene=str(data["scene"]),
                effects=tuple(str(e) for e in data["effects"]),
                code_version=str(data["code_version"]),
                split_seed=int(data["split_seed"]),
                depth_crop_m=None if "depth_crop_m" not in data else tuple(float(v) for v in data["depth_crop_m"]),  # type: ignore[arg-type]
                depth_map_method=str(data.get("depth_map_method", "nearest_point")),
            )
        except (KeyError, TypeError, IndexError, ValueError) as err:
            raise DatasetError(f"dataset.json: missing or malformed field ({err!r})") from err
        if info.depth_crop_m is not None and (
            len(info.depth_crop_m) != 3 or not all(np.isfinite(v) and v > 0 for v in info.depth_crop_m)
        ):
            raise DatasetError(f"dataset.json: depth_crop_m must be 3 positive extents (m), got {info.depth_crop_m}")
        if info.depth_map_method not in DEPTH_MAP_METHODS:
            raise DatasetError(
                f"dataset.json: depth_map_method must be one of {', '.join(DEPTH_MAP_METHODS)}, "
                f"got {info.depth_map_method!r}"
            )
        if not (0 < info.image_height <= MAX_IMAGE_SIDE and 0 < info.image_width <= MAX_IMAGE_SIDE):
            raise DatasetError(
                f"dataset.json: image size must be 1-{MAX_IMAGE_SIDE} pixels a side, got "
                f"{info.image_height}x{info.image_width}"
            )
        if not info.depth_range_m[1] > info.depth_range_m[0]:
            raise DatasetError(
                f"dataset.json: depth_range_m must be (near, far) with far > near, got {info.depth_range_m}"
            )
        return info


@dataclasses.dataclass(frozen=True)
class SampleRecord:
    """One manifest line. ``grasp_pose`` is (x, y, z [m], theta_z [rad]) in ``world``;
    ``stamps_ns`` names capture times (e.g. ``tactile``, ``depth``) in ns."""

    sample_id: str
    object_name: str
    grasp_id: int
    finger: str
    grasp_pose: tuple[float, float, float, float]
    stamps_ns: dict[str, int]
    registration_fitness: float
    files: dict[str, str]
    sha256: dict[str, str]
    # The object's model in the gel frame as the depth-map was made (4x4), None where unknown.
    model_to_gel: tuple[tuple[float, ...], ...] | None = None
    # The gel's pose in world as the arm measured it, and the object's registered pose before
    # centring between the gels (4x4 each); None where unknown (older sessions).
    gel_to_world: tuple[tuple[float, ...], ...] | None = None
    model_to_world: tuple[tuple[float, ...], ...] | None = None

    def to_json(self) -> dict[str, Any]:
        data = {
            "sample_id": self.sample_id,
            "object": self.object_name,
            "grasp_id": self.grasp_id,
            "finger": self.finger,
            "grasp_pose": list(self.grasp_pose),
            "stamps_ns": dict(self.stamps_ns),
            "registration_fitness": self.registration_fitness,
            "files": dict(self.files),
            "sha256": dict(self.sha256),
        }
        if self.model_to_gel is not None:
            data["model_to_gel"] = [list(row) for row in self.model_to_gel]
        for name in ("gel_to_world", "model_to_world"):
            if getattr(self, name) is not None:
                data[name] = [list(row) for row in getattr(self, name)]
        return data

    @staticmethod
    def from_json(data: Any) -> "SampleRecord":
        if not isinstance(data, dict):
            raise DatasetError(f"manifest line is not a JSON object: {data!r}")
        try:
            pose = tuple(float(v) for v in data["grasp_pose"])
            record = SampleRecord(
                sample_id=str(data["sample_id"]),
                object_name=str(data["object"]),
                grasp_id=int(data["grasp_id"]),
                finger=str(data["finger"]),
                grasp_pose=pose,  # type: ignore[arg-type]
                stamps_ns={str(k): int(v) for k, v in data["stamps_ns"].items()},
                registration_fitness=float(data["registration_fitness"]),
                files={str(k): str(v) for k, v in data["files"].items()},
                sha256={str(k): str(v) for k, v in data["sha256"].items()},
                model_to_gel=None if "model_to_gel" not in data else rigid_transform_tuple(data["model_to_gel"]),
                gel_to_world=None
                if "gel_to_world" not in data
                else rigid_transform_tuple(data["gel_to_world"], "gel_to_world"),
                model_to_world=None
                if "model_to_world" not in data
                else rigid_transform_tuple(data["model_to_world"], "model_to_world"),
            )
        except (KeyError, TypeError, ValueError, AttributeError) as err:
            raise DatasetError(f"manifest line has a missing or malformed field ({err!r})") from err
        if len(pose) != 4:
            raise DatasetError(f"sample {record.sample_id}: grasp_pose needs 4 values, got {len(pose)}")
        if set(record.files) != set(FILE_KINDS) or set(record.sha256) != set(FILE_KINDS):
            raise DatasetError(f"sample {record.sample_id}: files and sha256 must name {FILE_KINDS}")
        if not SAMPLE_ID.match(record.sample_id):
            raise DatasetError(f"sample id {record.sample_id!r} must be 1-128 characters of [A-Za-z0-9_.-]")
        if record.files != sample_files(record.sample_id):
            # A path of one's own choosing (../x, /etc/x) would be read from outside the dataset.
            raise DatasetError(
                f"sample {record.sample_id}: files must be {sample_files(record.sample_id)} "
                f"(inside the dataset), got {record.files}"
            )
        return record

    @property
    def grasp_key(self) -> str:
        """Identifies the grasp: both fingers of a grasp share it."""
        return f"{self.object_name}/{self.grasp_id}"


def sample_files(sample_id: str) -> dict[str, str]:
    """Where a sample's files lie, relative to the dataset directory: the only place."""
    return {kind: f"{kind}/{sample_id}{_FILE_SUFFIX[kind]}" for kind in FILE_KINDS}


_LAST_ROW = np.array([0.0, 0.0, 0.0, 1.0])
_EYE3 = np.eye(3)


def rigid_transform_tuple(value: Any, name: str = "model_to_gel") -> tuple[tuple[float, ...], ...]:
    """A 4x4 rigid transform as nested tuples of floats; DatasetError naming ``name`` unless it is one.

    The tolerances are ``np.allclose``'s (rtol 1e-5; atol 1e-8 for the last row, 1e-6 for
    R Rᵀ = I), written out: a reader checks three transforms a sample, and ``allclose`` made
    most of the time a 2,400-sample dataset took to open."""
    matrix = np.asarray(value, dtype=np.float64)
    if (
        matrix.shape != (4, 4)
        or not np.isfinite(matrix).all()
        or not (np.abs(matrix[3] - _LAST_ROW) <= 1e-8 + 1e-5 * _LAST_ROW).all()
        or not (np.abs(matrix[:3, :3] @ matrix[:3, :3].T - _EYE3) <= 1e-6 + 1e-5 * _EYE3).all()
    ):
        raise DatasetError(f"{name} must be a finite 4x4 rigid transform, got {value!r}")
    return tuple(tuple(row) for row in matrix.tolist())


@dataclasses.dataclass
class Sample:
    """A record with its arrays: tactile images H x W x 3 uint8 RGB, depth-map H x W float32 m."""

    record: SampleRecord
    tactile_rgb: np.ndarray
    tactile_diff_rgb: np.ndarray
    depth_map_m: np.ndarray


@dataclasses.dataclass(frozen=True)
class EncodedSample:
    """A checked sample with its files' bytes, ready for ``DatasetWriter.write_together``."""

    record: SampleRecord
    payloads: dict[str, bytes]


def code_version() -> str:
    """Package version plus the git commit of the checkout when there is one."""
    from importlib.metadata import PackageNotFoundError, version  # noqa: PLC0415 - read once per dataset

    try:
        text = f"dtx {version('dtx')}"
    except PackageNotFoundError:
        text = "dtx (not installed)"
    head = Path(__file__).resolve().parent.parent / ".git" / "HEAD"
    try:
        ref = head.read_text().strip()
        if ref.startswith("ref: "):
            ref = (head.parent / ref[5:]).read_text().strip()
        text += f" git {ref[:12]}"
    except OSError:
        pass
    return text
