"""Readers trust no file: malicious datasets and bags give a clear error, read nothing outside
the dataset, never hang and stay within 1 GiB of memory (each case runs in a subprocess
whose address space is capped at 1 GiB above what its imports took)."""

from __future__ import annotations

import hashlib
import json
import os
import stat
import struct
import subprocess
import sys
import tempfile
import textwrap
from pathlib import Path

import numpy as np
import pytest
import zstandard
from mcap.data_stream import RecordBuilder
from mcap.records import Chunk, Header
from mcap.writer import CompressionType, Writer

import msgs
from bus.bag_format import MESSAGE_ENCODING, SCHEMA_ENCODING, pack_frames
from dataset.images import subtract_background
from dataset.records import DatasetInfo
from dataset.writer import DatasetWriter
from msgs.codec import encode

MAGIC = b"\x89MCAP0\r\n"
INFO = DatasetInfo(
    image_height=100,
    image_width=100,
    depth_range_m=(-0.0015, 0.0025),
    scene="test",
    effects=("none",),
    code_version="test",
    split_seed=3,
)


def run_capped(body: str, timeout_s: float = 120.0) -> dict:
    """Run ``body`` (which sets ``result``) in a fresh interpreter capped at 1 GiB of address
    space above its imports; its result, as JSON."""
    script = (
        textwrap.dedent("""
        import json, resource
        from dataset.check import check_dataset
        from bus.bag import bag_info, iter_envelopes
        from bus.bag_format import BagError
        vm = next(int(line.split()[1]) * 1024 for line in open("/proc/self/status") if line.startswith("VmSize:"))
        resource.setrlimit(resource.RLIMIT_AS, (vm + (1 << 30), vm + (1 << 30)))
        result = {}
    """)
        + textwrap.dedent(body)
        + "\nprint(json.dumps(result))\n"
    )
    done = subprocess.run(
        [sys.executable, "-c", script],
        capture_output=True,
        text=True,
        timeout=timeout_s,
        cwd=Path(__file__).parent.parent,
    )
    assert done.returncode == 0, done.stderr[-3000:]
    return json.loads(done.stdout.splitlines()[-1])


# -- datasets ----------------------------------------------------------------------------


def one_grasp_dataset(root: Path) -> None:
    writer = DatasetWriter(root, INFO)
    image = np.random.default_rng(0).integers(0, 256, (100, 100, 3), dtype=np.uint8)
    writer.write_together(
        [
            writer.encode(
                sample_id=f"g0-{finger}",
                object_name="mug",
                grasp_id=0,
                finger=finger,
                grasp_pose=(0, 0, 0, 0),
                registration_fitness=1.0,
                tactile_rgb=image,
                tactile_diff_rgb=subtract_background(image, image),
                depth_map_m=np.zeros((100, 100), np.float32),
            )
            for finger in ("left", "right")
        ]
    )


def edit_left(root: Path, kind: str, path: str | None = None, content: bytes | None = None) -> None:
    """Point the left sample's ``kind`` file at ``path`` and/or give it ``content``, with a
    matching checksum (whoever forges a file can forge its checksum too)."""
    manifest = root / "manifest.jsonl"
    lines = [json.loads(line) for line in manifest.read_text().splitlines()]
    if path is not None:
        lines[0]["files"][kind] = path
    if content is not None:
        lines[0]["sha256"][kind] = hashlib.sha256(content).hexdigest()
    manifest.write_text("".join(json.dumps(line) + "\n" for line in lines))


def png_bomb_header() -> bytes:
    """A PNG whose header claims 30000 x 30000 RGB (2.7 GB decoded) in a few bytes."""
    ihdr = struct.pack(">IIBBBBB", 30000, 30000, 8, 2, 0, 0, 0)
    return b"\x89PNG\r\n\x1a\n" + struct.pack(">I", 13) + b"IHDR" + ihdr + b"\0\0\0\0" + b"\0" * 64


def npy_claiming_40_gb() -> bytes:
    header = "{'descr': '<f4', 'fortran_order': False, 'shape': (100000, 100000), }"
    header += " " * (63 - len(header) % 64) + "\n"
    return b"\x93NUMPY\x01\x00" + struct.pack("<H", len(header)) + header.encode() + b"\0" * 4000


def make_malicious_datasets(base: Path) -> dict[str, str]:
    """Case name -> what its check must say; each dataset in ``base/<case>``."""
    outside = base / "outside"
    outside.mkdir()
    (outside / "secret.png").write_bytes(b"outside the dataset")
    cases: dict[str, str] = {}

    def case(name: str, expected: str) -> Path:
        root = base / name
        one_grasp_dataset(root)
        cases[name] = expected
        return root

    # The file outside is the sample's own, checksum and all: only its place is wrong.
    root = case("dotdot_path", "inside the dataset")
    os.rename(root / "tactile/g0-left.png", base / "dotdot.png")
    edit_left(root, "tactile", "../dotdot.png")
    root = case("absolute_path", "inside the dataset")
    os.rename(root / "tactile/g0-left.png", outside / "absolute.png")
    edit_left(root, "tactile", str(outside / "absolute.png"))
    root = case("symlinked_file", "symbolic link")
    os.rename(root / "tactile/g0-left.png", outside / "linked.png")
    (root / "tactile/g0-left.png").symlink_to(outside / "linked.png")
    root = case("symlinked_directory", "symbolic link")
    os.rename(root / "depth", outside / "depth")
    (root / "depth").symlink_to(outside / "depth")
    root = case("named_pipe", "not a regular file")
    (root / "depth/g0-left.npy").unlink()
    os.mkfifo(root / "depth/g0-left.npy")
    root = case("dev_zero", "not a regular file")  # a device node of /dev/zero's numbers, inside
    (root / "depth/g0-left.npy").unlink()
    os.mknod(root / "depth/g0-left.npy", stat.S_IFCHR | 0o600, os.makedev(1, 5))
    root = case("dev_zero_symlink", "symbolic link")
    (root / "depth/g0-left.npy").unlink()
    (root / "depth/g0-left.npy").symlink_to("/dev/zero")
    root = case("npy_claims_40_GB", "header says (100000, 100000)")
    (root / "depth/g0-left.npy").write_bytes(npy := npy_claiming_40_gb())
    edit_left(root, "depth", content=npy)
    root = case("png_bomb", "PNG header says 30000x30000")
    (root / "tactile/g0-left.png").write_bytes(png := png_bomb_header())
    edit_left(root, "tactile", content=png)
    root = case("manifest_is_a_pipe", "not a regular file")
    (root / "manifest.jsonl").unlink()
    os.mkfifo(root / "manifest.jsonl")
    root = case("huge_sample_file", "over the limit")
    with open(root / "tactile/g0-left.png", "r+b") as f:
        f.truncate(1 << 30)  # sparse: a gigabyte claimed, nothing stored
    return cases


@pytest.mark.skipif(os.geteuid() != 0, reason="making a device node needs root")
def test_malicious_datasets_are_refused_clearly_within_bounds(tmp_path: Path) -> None:
    cases = make_malicious_datasets(tmp_path)
    result = run_capped(
        f"""
        for name in {sorted(cases)!r}:
            report = check_dataset({str(tmp_path)!r} + "/" + name)
            result[name] = report.problems
    """,
        timeout_s=120,
    )
    for name, expected in cases.items():
        assert result[name] and any(expected in p for p in result[name]), (name, result[name])


# -- bags --------------------------------------------------------------------------------


def bag_with_chunk(path: Path, data: bytes, uncompressed_size: int, compression: str = "zstd") -> None:
    """A bag whose only chunk holds ``data`` and declares ``uncompressed_size``."""
    builder = RecordBuilder()
    Header(profile="dtx", library="test").write(builder)
    Chunk(
        compression=compression,
        data=data,
        message_start_time=0,
        message_end_time=0,
        uncompressed_crc=0,
        uncompressed_size=uncompressed_size,
    ).write(builder)
    path.write_bytes(MAGIC + builder.end())


def zstd_bomb(inflated_bytes: int) -> bytes:
    """Zeros that inflate to ``inflated_bytes``, compressed to some tens of kilobytes; the frame
    header does not state the size, as a streamed frame does not."""
    compressor = zstandard.ZstdCompressor().compressobj()
    block = bytes(1 << 20)
    out = [compressor.compress(block) for _ in range(inflated_bytes >> 20)]
    return b"".join(out) + compressor.flush()


def bag_with_message(path: Path, data: bytes) -> None:
    with open(path, "wb") as f:
        writer = Writer(f, compression=CompressionType.ZSTD)
        writer.start(profile="dtx", library="test")
        schema = writer.register_schema("dtx.sensors.DepthImage", SCHEMA_ENCODING, b"{}")
        channel = writer.register_channel("/camera/depth", MESSAGE_ENCODING, schema)
        writer.add_message(channel, 1, data, 1)
        writer.finish()


def make_malicious_bags(base: Path) -> dict[str, str]:
    cases = {}
    bomb = zstd_bomb(1 << 30)
    bag_with_chunk(base / "zstd_bomb_1_GB.mcap", bomb, 1 << 30)  # what it claims is what it holds
    cases["zstd_bomb_1_GB.mcap"] = "over the limit"
    bag_with_chunk(base / "zstd_bomb_claims_1_kB.mcap", bomb, 1024)
    cases["zstd_bomb_claims_1_kB.mcap"] = "declares 1024 bytes uncompressed but holds more"
    (base / "record_claims_10_GB.mcap").write_bytes(MAGIC + struct.pack("<BQ", 0x01, 10 << 30) + b"x" * 64)
    cases["record_claims_10_GB.mcap"] = "limit"
    frames = encode("/camera/depth", msgs.DepthImage(depth=np.zeros((2, 2), np.uint16)), "test")
    # The depth array's shape [2, 2] becomes [10^5, 10^5] (20 GB of uint16); its buffer stays 8 bytes.
    forged = frames[1].replace(b"\x92\x02\x02", b"\x92\xce\x00\x01\x86\xa0\xce\x00\x01\x86\xa0")
    assert frames[1].count(b"\x92\x02\x02") == 1
    bag_with_message(base / "array_claims_10_GB.mcap", pack_frames([forged, *frames[2:]]))
    cases["array_claims_10_GB.mcap"] = "not a valid dtx message"
    bag_with_message(base / "frame_claims_10_GB.mcap", struct.pack("<Q", 10 << 30) + b"\0" * 64)
    cases["frame_claims_10_GB.mcap"] = "announces 10737418240 bytes"
    os.mkfifo(base / "named_pipe.mcap")
    cases["named_pipe.mcap"] = "not a regular file"
    return cases


def test_malicious_bags_are_refused_clearly_within_bounds(tmp_path: Path) -> None:
    cases = make_malicious_bags(tmp_path)
    result = run_capped(
        f"""
        for name in {sorted(cases)!r}:
            path = {str(tmp_path)!r} + "/" + name
            for reader in ("info", "play"):
                try:
                    bag_info(path) if reader == "info" else list(iter_envelopes(path))
                    result[name + " " + reader] = "read without an error"
                except BagError as error:
                    result[name + " " + reader] = str(error)
    """,
        timeout_s=120,
    )
    decoded_only_in_play = {"array_claims_10_GB.mcap", "frame_claims_10_GB.mcap"}  # info counts records
    for name, expected in cases.items():
        assert expected in result[f"{name} play"], (name, result[f"{name} play"])
        info = result[f"{name} info"]
        assert info == "read without an error" if name in decoded_only_in_play else expected in info, (name, info)


def test_bag_play_and_replay_end_with_a_clear_error_on_a_bad_bag(tmp_path: Path) -> None:
    bag_with_chunk(tmp_path / "bomb.mcap", zstd_bomb(8 << 20), 4 << 30)
    with tempfile.TemporaryDirectory(prefix="dtxu") as bus_dir:
        env = {**os.environ, "DTX_BUS_DIR": bus_dir}
        play = subprocess.run(
            [sys.executable, "-m", "dtx.cli", "bag", "play", str(tmp_path / "bomb.mcap"), "--fast"],
            capture_output=True,
            text=True,
            timeout=120,
            env=env,
        )
        assert play.returncode == 1 and "bag play stopped" in play.stderr and "over the limit" in play.stderr
        replay = subprocess.run(
            [
                sys.executable,
                "-m",
                "dtx.cli",
                "launch",
                "launch/replay.yaml",
                f"bag:={tmp_path / 'bomb.mcap'}",
                f"out:={tmp_path / 'replayed'}",
            ],
            capture_output=True,
            text=True,
            timeout=120,
            env=env,
        )
    assert replay.returncode != 0, replay.stdout[-2000:]
    assert "the bag could not be played to its end" in replay.stdout, replay.stdout[-2000:]
