"""The on-disk tactile experience dataset: writer, reader and checks.

Layout of a dataset directory ``DIR``::

    DIR/dataset.json          format name + version, image size, depth_range_m, scene,
                              effects, code version, split seed (written once)
    DIR/manifest.jsonl        one JSON object per sample, appended after its files exist
    DIR/tactile/<id>.png      GelSight image, RGB, as captured (viewable)
    DIR/tactile_diff/<id>.png background-subtracted copy: image - background + 128, RGB
    DIR/depth/<id>.npy        contact depth-map, float32 metres in the gel frame
                              (min y per bin; NaN or +inf = empty bin), np.save format

Crash safety: every file of a sample goes to a temporary name, is fsynced and renamed into
place; only then is the manifest line appended and fsynced. A sample therefore exists
exactly when its manifest line does. Files left without a manifest line by a crash are
overwritten when the sample is written again on resume. A torn last manifest line (the
process died mid-append) is cut off when a writer reopens the dataset.

A grasp's fingers land together: ``write_together`` writes every file of both samples first
and then appends their manifest lines in one write, so a crash at any point leaves both or
neither. Should an append still be torn between the lines, ``drop_incomplete_grasps`` (a
collector resuming) removes the lone finger so the whole grasp is redone.
"""

from __future__ import annotations

import dataclasses
import errno
import hashlib
import io
import json
import os
import re
import stat
import struct
from collections.abc import Iterator, Sequence
from pathlib import Path
from typing import Any

import cv2
import numpy as np

FORMAT_NAME = "dtx-tactile-dataset"
FORMAT_VERSION = 1
FINGERS = ("left", "right")
FILE_KINDS = ("tactile", "tactile_diff", "depth")
_FILE_SUFFIX = {"tactile": ".png", "tactile_diff": ".png", "depth": ".npy"}
_SAMPLE_ID = re.compile(r"^[A-Za-z0-9][A-Za-z0-9_.-]{0,127}$")
_DIFF_OFFSET = 128
# Readers trust no file: sizes are bounded before anything is read or allocated.
MAX_IMAGE_SIDE = 4096
_MAX_INFO_BYTES = 1 << 20
_MAX_MANIFEST_BYTES = 256 << 20
_PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"


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
            )
        except (KeyError, TypeError, IndexError, ValueError) as err:
            raise DatasetError(f"dataset.json: missing or malformed field ({err!r})") from err
        if info.depth_crop_m is not None and (
            len(info.depth_crop_m) != 3 or not all(np.isfinite(v) and v > 0 for v in info.depth_crop_m)
        ):
            raise DatasetError(f"dataset.json: depth_crop_m must be 3 positive extents (m), got {info.depth_crop_m}")
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
                model_to_gel=None if "model_to_gel" not in data else _transform_tuple(data["model_to_gel"]),
            )
        except (KeyError, TypeError, ValueError, AttributeError) as err:
            raise DatasetError(f"manifest line has a missing or malformed field ({err!r})") from err
        if len(pose) != 4:
            raise DatasetError(f"sample {record.sample_id}: grasp_pose needs 4 values, got {len(pose)}")
        if set(record.files) != set(FILE_KINDS) or set(record.sha256) != set(FILE_KINDS):
            raise DatasetError(f"sample {record.sample_id}: files and sha256 must name {FILE_KINDS}")
        if not _SAMPLE_ID.match(record.sample_id):
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


def _transform_tuple(value: Any) -> tuple[tuple[float, ...], ...]:
    """A 4x4 rigid transform as nested tuples of floats; DatasetError unless it is one."""
    matrix = np.asarray(value, dtype=np.float64)
    if (
        matrix.shape != (4, 4)
        or not np.all(np.isfinite(matrix))
        or not np.allclose(matrix[3], [0, 0, 0, 1])
        or not np.allclose(matrix[:3, :3] @ matrix[:3, :3].T, np.eye(3), atol=1e-6)
    ):
        raise DatasetError(f"model_to_gel must be a finite 4x4 rigid transform, got {value!r}")
    return tuple(tuple(float(v) for v in row) for row in matrix)


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


def subtract_background(image_rgb: np.ndarray, background_rgb: np.ndarray) -> np.ndarray:
    """The background-subtracted copy stored beside each image: image - background + 128,
    clipped to uint8, so that no change reads as mid-grey and the file stays viewable."""
    image = _check_rgb(image_rgb, "image")
    background = _check_rgb(background_rgb, "background")
    if image.shape != background.shape:
        raise DatasetError(f"image {image.shape} and background {background.shape} differ in shape")
    diff = image.astype(np.int16) - background.astype(np.int16) + _DIFF_OFFSET
    return np.clip(diff, 0, 255).astype(np.uint8)


def resize_rgb(image_rgb: np.ndarray, height: int, width: int) -> np.ndarray:
    """An H x W x 3 image at ``height`` x ``width``: area-averaged when it shrinks (no aliasing
    of the gel's fine shading), bilinear when it grows; the same array when the size is right."""
    if image_rgb.shape[:2] == (height, width):
        return image_rgb
    shrink = image_rgb.shape[0] > height
    return cv2.resize(
        np.ascontiguousarray(image_rgb), (width, height), interpolation=cv2.INTER_AREA if shrink else cv2.INTER_LINEAR
    )


def deformation_map(tactile_diff_rgb: np.ndarray) -> np.ndarray:
    """Per-pixel deformation strength (H x W float32): summed |change| over RGB from the
    background-subtracted copy."""
    diff = _check_rgb(tactile_diff_rgb, "tactile_diff").astype(np.float32) - _DIFF_OFFSET
    return np.abs(diff).sum(axis=2)


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


def _check_rgb(array: np.ndarray, name: str) -> np.ndarray:
    array = np.asarray(array)
    if array.dtype != np.uint8 or array.ndim != 3 or array.shape[2] != 3:
        raise DatasetError(f"{name} must be H x W x 3 uint8 RGB, got {array.shape} {array.dtype}")
    return array


def _sha256(data: bytes) -> str:
    return hashlib.sha256(data).hexdigest()


def _encode_png(rgb: np.ndarray) -> bytes:
    ok, buf = cv2.imencode(".png", cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR))
    if not ok:
        raise DatasetError("PNG encoding failed")
    return buf.tobytes()


def _decode_png(data: bytes, name: str, shape: tuple[int, int]) -> np.ndarray:
    """An 8-bit RGB PNG of ``shape`` (H, W): the header is checked before decoding, so a
    small file claiming a huge image is refused without the decoder allocating it."""
    if len(data) < 33 or data[:8] != _PNG_SIGNATURE or data[12:16] != b"IHDR":
        raise DatasetError(f"{name}: not a PNG file")
    width, height = struct.unpack(">II", data[16:24])
    if (height, width) != shape or data[24:26] != b"\x08\x02":
        raise DatasetError(
            f"{name}: PNG header says {height}x{width} (bit depth {data[24]}, colour type "
            f"{data[25]}); dataset images are {shape[0]}x{shape[1]} 8-bit RGB"
        )
    bgr = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_UNCHANGED)
    if bgr is None or bgr.ndim != 3 or bgr.shape[2] != 3 or bgr.dtype != np.uint8:
        raise DatasetError(f"{name}: not an 8-bit RGB PNG")
    return cv2.cvtColor(bgr, cv2.COLOR_BGR2RGB)


def _encode_npy(depth_map_m: np.ndarray) -> bytes:
    buf = io.BytesIO()
    np.save(buf, depth_map_m, allow_pickle=False)
    return buf.getvalue()


def _decode_npy(data: bytes, name: str, shape: tuple[int, int]) -> np.ndarray:
    """A float32 array of ``shape`` from .npy bytes: the header's shape and dtype are checked
    before anything is allocated, so a header claiming 40 GB is refused, not attempted."""
    stream = io.BytesIO(data)
    try:
        version = np.lib.format.read_magic(stream)
        read_header = {(1, 0): np.lib.format.read_array_header_1_0, (2, 0): np.lib.format.read_array_header_2_0}.get(
            version
        )
        if read_header is None:
            raise ValueError(f"format version {version} is not one this reader takes")
        stored_shape, fortran, dtype = read_header(stream, max_header_size=4096)
    except (ValueError, OSError, EOFError, SyntaxError) as err:
        raise DatasetError(f"{name}: not a readable .npy array ({err})") from err
    if stored_shape != shape or dtype != np.dtype("<f4") or fortran:
        raise DatasetError(
            f"{name}: .npy header says {stored_shape} {dtype}{' (Fortran order)' if fortran else ''}; "
            f"depth-maps are {shape} little-endian float32"
        )
    if len(data) - stream.tell() != 4 * shape[0] * shape[1]:
        raise DatasetError(
            f"{name}: .npy holds {len(data) - stream.tell()} data bytes, its header says {4 * shape[0] * shape[1]}"
        )
    return np.frombuffer(data, np.float32, offset=stream.tell()).reshape(shape).copy()


def read_regular_file(path: Path, limit: int, what: str) -> bytes:
    """The bytes of ``path``, which must be a regular file (not a symbolic link) of at most
    ``limit`` bytes. A named pipe would block a reader forever and /dev/zero never ends, so
    the kind and size are checked on the open file before a byte is read. OSError where the
    file cannot be opened; DatasetError where it is not one to read."""
    try:
        fd = os.open(path, os.O_RDONLY | os.O_NOFOLLOW | os.O_NONBLOCK | os.O_CLOEXEC)
    except OSError as err:
        if err.errno == errno.ELOOP:
            raise DatasetError(f"{what} {path} is a symbolic link: a dataset holds its own files") from err
        raise
    try:
        info = os.fstat(fd)
        if not stat.S_ISREG(info.st_mode):
            raise DatasetError(f"{what} {path} is not a regular file")
        if info.st_size > limit:
            raise DatasetError(f"{what} {path} is {info.st_size} bytes, over the limit of {limit}")
        chunks, total = [], 0
        while chunk := os.read(fd, min(1 << 20, limit + 1 - total)):
            chunks.append(chunk)
            total += len(chunk)
            if total > limit:
                raise DatasetError(f"{what} {path} grew past the limit of {limit} bytes while read")
        return b"".join(chunks)
    finally:
        os.close(fd)


def _fsync_dir(path: Path) -> None:
    fd = os.open(path, os.O_RDONLY)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)


def _write_atomic(path: Path, data: bytes) -> None:
    """Write ``data`` to ``path`` so that a crash leaves either the old file or the new one."""
    tmp = path.with_name(f".{path.name}.tmp")
    try:
        with open(tmp, "wb") as f:
            f.write(data)
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise


def _check_sample_arrays(
    info: DatasetInfo, tactile_rgb: np.ndarray, tactile_diff_rgb: np.ndarray, depth_map_m: np.ndarray, sample_id: str
) -> None:
    shape = (info.image_height, info.image_width)
    for name, image in (("tactile", tactile_rgb), ("tactile_diff", tactile_diff_rgb)):
        image = _check_rgb(image, f"sample {sample_id}: {name}")
        if image.shape[:2] != shape:
            raise DatasetError(f"sample {sample_id}: {name} is {image.shape[:2]}, dataset images are {shape}")
    depth = np.asarray(depth_map_m)
    if depth.dtype != np.float32 or depth.shape != shape:
        raise DatasetError(
            f"sample {sample_id}: depth-map must be {shape} float32 metres, got {depth.shape} {depth.dtype}"
        )
    if np.any(np.isneginf(depth)):
        raise DatasetError(f"sample {sample_id}: depth-map contains -inf (empty bins are NaN or +inf)")


class DatasetWriter:
    """Appends samples to a dataset directory; reopening an existing dataset resumes it.

    ``info`` is required for a new dataset; for an existing one it may be omitted, and if
    given must equal what is stored (one dataset, one normalisation and one scene).
    """

    def __init__(self, root: str | os.PathLike[str], info: DatasetInfo | None = None) -> None:
        self.root = Path(root)
        try:
            self.root.mkdir(parents=True, exist_ok=True)
            for kind in FILE_KINDS:
                (self.root / kind).mkdir(exist_ok=True)
            _check_own_directories(self.root)
            meta_path = self.root / "dataset.json"
            if meta_path.exists():
                stored = _read_info(meta_path)
                if info is not None and info != stored:
                    raise DatasetError(f"{self.root}: dataset.json holds {stored}, not the given {info}")
                self.info = stored
            else:
                if info is None:
                    raise DatasetError(f"{self.root} is not a dataset yet: DatasetInfo is required")
                _write_atomic(meta_path, (json.dumps(info.to_json(), indent=2) + "\n").encode())
                _fsync_dir(self.root)
                self.info = info
            self._manifest = self.root / "manifest.jsonl"
            self._manifest.touch(exist_ok=True)
            self._repair_torn_tail()
        except OSError as err:
            raise DatasetError(f"cannot open dataset {self.root} for writing: {err}") from err
        self.records: list[SampleRecord] = _read_manifest(self._manifest)
        self._ids = {r.sample_id for r in self.records}

    def __len__(self) -> int:
        return len(self.records)

    def __contains__(self, sample_id: str) -> bool:
        return sample_id in self._ids

    def _repair_torn_tail(self) -> None:
        data = read_regular_file(self._manifest, _MAX_MANIFEST_BYTES, "manifest")
        if data and not data.endswith(b"\n"):
            keep = data.rfind(b"\n") + 1
            with open(self._manifest, "r+b") as f:
                f.truncate(keep)
                os.fsync(f.fileno())

    def encode(
        self,
        *,
        sample_id: str,
        object_name: str,
        grasp_id: int,
        finger: str,
        grasp_pose: Sequence[float],
        tactile_rgb: np.ndarray,
        tactile_diff_rgb: np.ndarray,
        depth_map_m: np.ndarray,
        registration_fitness: float,
        stamps_ns: dict[str, int] | None = None,
        model_to_gel: np.ndarray | None = None,
    ) -> EncodedSample:
        """Check one sample and encode its files, touching nothing on disk: ``write_together``
        then lands it (with its grasp's other finger). DatasetError for bad arrays or fields."""
        if not isinstance(sample_id, str) or not _SAMPLE_ID.match(sample_id):
            raise DatasetError(
                f"sample id {sample_id!r} must be 1-128 characters of [A-Za-z0-9_.-], not starting with '.', '_' or '-'"
            )
        if finger not in FINGERS:
            raise DatasetError(f"sample {sample_id}: finger must be one of {FINGERS}, got {finger!r}")
        pose = tuple(float(v) for v in grasp_pose)
        if len(pose) != 4 or not all(np.isfinite(pose)):
            raise DatasetError(
                f"sample {sample_id}: grasp_pose must be 4 finite numbers "
                f"(x, y, z [m], theta_z [rad]), got {grasp_pose}"
            )
        if not np.isfinite(registration_fitness):
            raise DatasetError(f"sample {sample_id}: registration_fitness must be finite, got {registration_fitness}")
        _check_sample_arrays(self.info, tactile_rgb, tactile_diff_rgb, depth_map_m, sample_id)
        try:
            transform = None if model_to_gel is None else _transform_tuple(model_to_gel)
        except DatasetError as err:
            raise DatasetError(f"sample {sample_id}: {err}") from err

        payloads = {
            "tactile": _encode_png(np.asarray(tactile_rgb)),
            "tactile_diff": _encode_png(np.asarray(tactile_diff_rgb)),
            "depth": _encode_npy(np.asarray(depth_map_m)),
        }
        files = sample_files(sample_id)
        record = SampleRecord(
            sample_id=sample_id,
            object_name=str(object_name),
            grasp_id=int(grasp_id),
            finger=finger,
            grasp_pose=pose,
            stamps_ns={str(k): int(v) for k, v in (stamps_ns or {}).items()},  # type: ignore[arg-type]
            registration_fitness=float(registration_fitness),
            files=files,
            sha256={kind: _sha256(data) for kind, data in payloads.items()},
            model_to_gel=transform,
        )
        return EncodedSample(record, payloads)

    def write(self, **fields: Any) -> SampleRecord:
        """Write one sample (``fields`` as for ``encode``) atomically and return its record."""
        return self.write_together([self.encode(**fields)])[0]

    def write_together(self, samples: Sequence[EncodedSample]) -> list[SampleRecord]:
        """Land several samples (a grasp's two fingers) together: all of them, or none.

        Every file of every sample is written first; their manifest lines follow in one
        append, so a crash or a full disk at any point leaves either all the samples or none
        (their files, orphaned, are overwritten on resume). Raises DatasetError for a repeated
        sample id and for a disk error; the dataset is left as it was.
        """
        ids = [s.record.sample_id for s in samples]
        repeated = sorted({i for i in ids if i in self._ids or ids.count(i) > 1})
        if repeated:
            raise DatasetError(f"sample(s) {repeated} already in {self.root} or given twice: refusing a duplicate")
        lines = b"".join((json.dumps(s.record.to_json(), allow_nan=False) + "\n").encode() for s in samples)
        try:
            for sample in samples:
                for kind, data in sample.payloads.items():
                    _write_atomic(self.root / sample.record.files[kind], data)
            for kind in FILE_KINDS:
                _fsync_dir(self.root / kind)
            self._append_manifest(lines)
        except OSError as err:
            raise DatasetError(
                f"could not write sample {' and '.join(ids)} to {self.root}: {err} "
                "(the dataset is intact; free space or fix permissions and resume)"
            ) from err
        self.records += [s.record for s in samples]
        self._ids.update(ids)
        return [s.record for s in samples]

    def drop_incomplete_grasps(self) -> list[str]:
        """Remove from the manifest every sample whose grasp lacks one of the fingers, and
        return their ids: a resuming collector then redoes those grasps whole, so no grasp
        pairs a finger of one attempt with a finger of another. Their files stay, to be
        overwritten by the redo."""
        fingers: dict[str, set[str]] = {}
        for record in self.records:
            fingers.setdefault(record.grasp_key, set()).add(record.finger)
        lone = [r for r in self.records if fingers[r.grasp_key] != set(FINGERS)]
        if not lone:
            return []
        keep = [r for r in self.records if fingers[r.grasp_key] == set(FINGERS)]
        text = "".join(json.dumps(r.to_json(), allow_nan=False) + "\n" for r in keep).encode()
        try:
            _write_atomic(self._manifest, text)
            _fsync_dir(self.root)
        except OSError as err:
            raise DatasetError(f"could not rewrite the manifest of {self.root}: {err} (it is intact)") from err
        self.records = keep
        self._ids = {r.sample_id for r in keep}
        return [r.sample_id for r in lone]

    def _append_manifest(self, lines: bytes) -> None:
        with open(self._manifest, "ab") as f:
            size = f.tell()
            try:
                f.write(lines)
                f.flush()
                os.fsync(f.fileno())
            except OSError:
                # A partial append would corrupt the manifest or split a grasp: cut it all back.
                f.truncate(size)
                raise


def _check_own_directories(root: Path) -> None:
    """The file directories must be the dataset's own: a symbolic link would read (or write)
    samples outside it."""
    for kind in FILE_KINDS:
        if (root / kind).is_symlink():
            raise DatasetError(f"{root / kind} is a symbolic link: a dataset holds its own files")


def _read_info(path: Path) -> DatasetInfo:
    try:
        data = json.loads(read_regular_file(path, _MAX_INFO_BYTES, "dataset info"))
    except DatasetError:
        raise
    except FileNotFoundError as err:
        raise DatasetError(f"{path.parent} is not a dataset: {path.name} is missing") from err
    except (OSError, ValueError) as err:
        raise DatasetError(f"{path}: unreadable ({err})") from err
    if not isinstance(data, dict):
        raise DatasetError(f"{path}: not a JSON object")
    return DatasetInfo.from_json(data)


def _read_manifest(path: Path) -> list[SampleRecord]:
    try:
        text = read_regular_file(path, _MAX_MANIFEST_BYTES, "manifest").decode("utf-8")
    except FileNotFoundError as err:
        raise DatasetError(f"{path.parent}: manifest.jsonl is missing") from err
    except (OSError, UnicodeDecodeError) as err:
        raise DatasetError(f"{path}: unreadable ({err})") from err
    if text and not text.endswith("\n"):
        raise DatasetError(
            f"{path}: last line is incomplete (a writer died mid-append; "
            "reopening the dataset with DatasetWriter repairs it)"
        )
    records = []
    for number, line in enumerate(text.splitlines(), start=1):
        try:
            records.append(SampleRecord.from_json(json.loads(line)))
        except (json.JSONDecodeError, DatasetError) as err:
            raise DatasetError(f"{path}:{number}: corrupt manifest line ({err})") from err
    return records


class DatasetReader:
    """Reads a dataset; ``load`` verifies the checksums of the files it reads."""

    def __init__(self, root: str | os.PathLike[str]) -> None:
        self.root = Path(root)
        if not self.root.is_dir():
            raise DatasetError(f"dataset directory {self.root} does not exist")
        self.info = _read_info(self.root / "dataset.json")
        self.records = _read_manifest(self.root / "manifest.jsonl")
        _check_own_directories(self.root)
        self._by_id: dict[str, SampleRecord] = {}
        for record in self.records:
            if record.sample_id in self._by_id:
                raise DatasetError(f"{self.root}: sample {record.sample_id} appears twice in the manifest")
            self._by_id[record.sample_id] = record

    def __len__(self) -> int:
        return len(self.records)

    def __iter__(self) -> Iterator[Sample]:
        return (self.load(record) for record in self.records)

    def record(self, sample_id: str) -> SampleRecord:
        try:
            return self._by_id[sample_id]
        except KeyError as err:
            raise DatasetError(f"{self.root}: no sample {sample_id!r}") from err

    def load(self, sample: SampleRecord | str, verify: bool = True) -> Sample:
        record = self.record(sample) if isinstance(sample, str) else sample
        raw = {}
        shape = (self.info.image_height, self.info.image_width)
        limit = (1 << 20) + 8 * shape[0] * shape[1]  # an uncompressed PNG or .npy of this size, and then some
        for kind in FILE_KINDS:
            path = self.root / record.files[kind]
            try:
                raw[kind] = read_regular_file(path, limit, f"sample {record.sample_id}: file")
            except OSError as err:
                raise DatasetError(f"sample {record.sample_id}: cannot read {path} ({err})") from err
            if verify and _sha256(raw[kind]) != record.sha256[kind]:
                raise DatasetError(f"sample {record.sample_id}: checksum mismatch for {path}")
        sample_obj = Sample(
            record=record,
            tactile_rgb=_decode_png(raw["tactile"], record.files["tactile"], shape),
            tactile_diff_rgb=_decode_png(raw["tactile_diff"], record.files["tactile_diff"], shape),
            depth_map_m=_decode_npy(raw["depth"], record.files["depth"], shape),
        )
        _check_sample_arrays(
            self.info, sample_obj.tactile_rgb, sample_obj.tactile_diff_rgb, sample_obj.depth_map_m, record.sample_id
        )
        return sample_obj
