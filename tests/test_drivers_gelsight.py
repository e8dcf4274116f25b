"""GelSight V4L2 backend: real GelSight frames played back from a video, camera discovery
on a sysfs tree laid out like the kernel's, and the end / loss of a stream."""

from __future__ import annotations

import os
import threading
import time
from pathlib import Path

import cv2
import numpy as np
import pytest

from drivers.gelsight import EndOfStreamError, GelSightError, make_backend
from drivers.gelsight.base import PRESETS, GelSightTimeoutError
from drivers.gelsight.v4l2 import FrameSource, find_camera

ASSET = Path(__file__).resolve().parent.parent / "assets" / "gelsight" / "ball_presses.npz"
WARMUP, BACKGROUND = 3, 4


@pytest.fixture(scope="module")
def presses():
    with np.load(ASSET) as data:
        return data["background"], data["frames"]


@pytest.fixture
def video(tmp_path, presses):
    """Warm-up and no-contact frames, then the 30 real ball presses, losslessly (FFV1)."""
    background, frames = presses
    path = tmp_path / "presses.avi"
    writer = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"FFV1"), 30, (background.shape[1], background.shape[0]))
    assert writer.isOpened()
    for rgb in [background] * (WARMUP + BACKGROUND) + list(frames):
        writer.write(cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR))
    writer.release()
    return path


def play(video, **params):
    sensor = make_backend(
        {
            "backend": "v4l2",
            "video_file": str(video),
            "warmup_frames": WARMUP,
            "background_frames": BACKGROUND,
            **params,
        }
    )
    sensor.connect()
    return sensor


def test_plays_real_frames_with_background(video, presses):
    background, frames = presses
    sensor = play(video, sensor="right")
    try:
        assert np.array_equal(sensor.background, background)
        for expected in frames:
            tactile = sensor.read()
            assert np.array_equal(tactile.image, expected)
            assert np.array_equal(tactile.background, background)
        assert tactile.sensor == "right"
        assert tactile.header.frame_id == "gel_right"
        assert tactile.mm_per_px == pytest.approx(0.1245)
    finally:
        sensor.disconnect()


def test_video_that_ends_raises_end_of_stream(video):
    sensor = play(video)
    try:
        for _ in range(30):
            sensor.read()
        with pytest.raises(EndOfStreamError, match=r"presses.avi ended after 37 frames"):
            sensor.read()
    finally:
        sensor.disconnect()


def test_looping_video_starts_over(video, presses):
    background, frames = presses
    sensor = play(video, loop_video=True)
    try:
        for _ in range(30):
            sensor.read()
        assert np.array_equal(sensor.read().image, background)  # first frame again
    finally:
        sensor.disconnect()


def test_camera_that_stops_delivering_frames(video):
    """A live source whose frames stop (here: a file that runs out) reports a lost camera."""
    source = FrameSource(
        cv2.VideoCapture(str(video)),
        "/dev/video4 (GelSight Mini, USB 1-2)",
        live=True,
        max_failed_reads=3,
        deadline_s=10.0,
    )
    try:
        for _ in range(37):
            source.next_rgb()
        with pytest.raises(GelSightError, match=r"/dev/video4 .* stopped delivering frames after 37"):
            source.next_rgb()
    finally:
        source.release()


class SilentCamera:
    """A capture whose read() never returns until released: a camera that stopped answering
    inside the driver (OpenCV's V4L2 read then waits its select time-out, 10 s, per try)."""

    def __init__(self) -> None:
        self.answer = threading.Event()

    def read(self) -> tuple[bool, np.ndarray]:
        self.answer.wait()
        return True, np.zeros((240, 320, 3), np.uint8)


def test_a_camera_that_stops_answering_fails_the_read_within_its_deadline():
    camera = SilentCamera()
    source = FrameSource(camera, "/dev/video4", live=True, max_failed_reads=3, deadline_s=0.2)  # type: ignore[arg-type]
    with pytest.raises(GelSightTimeoutError, match="/dev/video4: read a frame: no answer within 0.2 s"):
        source.next_rgb()
    with pytest.raises(GelSightTimeoutError, match="an earlier read past its deadline has not returned"):
        source.next_rgb()
    camera.answer.set()
    deadline = time.monotonic() + 10.0
    while True:  # the late read returns and frees the camera
        try:
            assert source.next_rgb().shape == (240, 320, 3)
            break
        except GelSightTimeoutError:
            assert time.monotonic() < deadline, "the late read never freed the camera"
            time.sleep(0.01)


def test_missing_video_file(tmp_path):
    with pytest.raises(GelSightError, match="does not exist"):
        play(tmp_path / "none.avi")


def test_preset_crops_margins_and_resizes():
    mini = PRESETS["gelsight_mini"]
    frame = np.zeros((240, 320, 3), np.uint8)
    frame[34:206, 46:274] = 200  # the gel area inside a seventh-wide dark rim
    out = mini.crop_and_resize(frame)
    assert out.shape == (240, 320, 3)
    assert out.min() == 200


def make_sysfs(root: Path, nodes: list[tuple[int, str, int, str]]) -> Path:
    """video<N>/{name,index,device->.../<port>:1.0} as the kernel lays them out."""
    for number, name, index, port in nodes:
        node = root / "class" / f"video{number}"
        interface = root / "devices" / "usb1" / port / f"{port}:1.0"
        interface.mkdir(parents=True, exist_ok=True)
        node.mkdir(parents=True)
        (node / "name").write_text(name + "\n")
        (node / "index").write_text(f"{index}\n")
        os.symlink(interface, node / "device")
    return root / "class"


@pytest.fixture
def sysfs(tmp_path):
    return str(
        make_sysfs(
            tmp_path,
            [
                (0, "GelSight Mini R0B 28J3-CWXU: Ge", 0, "1-2"),
                (1, "GelSight Mini R0B 28J3-CWXU: Ge", 1, "1-2"),  # its metadata node
                (2, "GelSight Mini R0B 2BNK-CE0U: Ge", 0, "1-3"),
                (4, "Integrated Camera: Integrated C", 0, "3-8"),
            ],
        )
    )


def test_finds_camera_by_name_and_port(sysfs):
    assert find_camera("gelsight mini", "1-3", sysfs).index == 2
    assert find_camera("Integrated", "", sysfs).index == 4


def test_two_identical_sensors_need_a_port(sysfs):
    with pytest.raises(GelSightError, match="2 cameras named like 'GelSight Mini'.*set usb_port"):
        find_camera("GelSight Mini", "", sysfs)


def test_absent_camera_lists_what_was_found(sysfs):
    with pytest.raises(
        GelSightError,
        match=r"no camera named like 'DIGIT'; cameras found: "
        r"/dev/video0 .*\(USB 1-2\).*/dev/video4",
    ):
        find_camera("DIGIT", "", sysfs)


def test_no_v4l2_at_all(tmp_path):
    with pytest.raises(GelSightError, match="no V4L2 cameras at all"):
        make_backend({"backend": "v4l2", "sysfs_root": str(tmp_path / "none")}).connect()


def test_unopenable_device_index():
    with pytest.raises(GelSightError, match=r"cannot open /dev/video63 through V4L2"):
        make_backend({"backend": "v4l2", "device_index": 63}).connect()


def test_unknown_preset_and_parameters():
    with pytest.raises(GelSightError, match=r"unknown GelSight preset 'digit'; known: \['gelsight', 'gelsight_mini'\]"):
        make_backend({"backend": "v4l2", "preset": "digit"})
    with pytest.raises(ValueError, match=r"unknown parameter\(s\) \['exposure'\]"):
        make_backend({"backend": "v4l2", "exposure": 3})
