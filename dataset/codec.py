"""A sample's files as bytes: 8-bit RGB PNG images and float32 .npy depth-maps, whose headers
are checked before anything is decoded or allocated (a reader trusts no file)."""

from __future__ import annotations

import io
import struct

import cv2
import numpy as np

from dataset.records import DatasetError

_PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"


def encode_png(rgb: np.ndarray) -> bytes:
    ok, buf = cv2.imencode(".png", cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR))
    if not ok:
        raise DatasetError("PNG encoding failed")
    return buf.tobytes()


def decode_png(data: bytes, name: str, shape: tuple[int, int]) -> np.ndarray:
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


def encode_npy(depth_map_m: np.ndarray) -> bytes:
    buf = io.BytesIO()
    np.save(buf, depth_map_m, allow_pickle=False)
    return buf.getvalue()


def decode_npy(data: bytes, name: str, shape: tuple[int, int]) -> np.ndarray:
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
