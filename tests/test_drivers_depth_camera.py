"""Depth camera backends against the real libOpenNI2 of this machine.

No Kinect is attached here, so the OpenNI2 backend streams from the "Dummy" device driver
that Debian's libopenni2-0 ships (a real OpenNI2 driver producing 320x240 millimetre frames),
records a real .oni file with OpenNI2's recorder, and checks every missing-piece error.
"""

from __future__ import annotations

import importlib.util
import time
from pathlib import Path

import numpy as np
import pytest
import yaml
from openni import openni2

from drivers.depth_camera import DepthCameraError, make_backend
from drivers.depth_camera.base import depth_image, load_calibration
from drivers.depth_camera.openni2 import load_openni2

LIBRARY_DIR = "/usr/lib/x86_64-linux-gnu"
LAUNCH = Path(__file__).resolve().parent.parent / "launch"
needs_openni2 = pytest.mark.skipif(
    not Path(LIBRARY_DIR, "libOpenNI2.so.0").exists(), reason="Debian's libopenni2-0 is not installed"
)


def write_calibration(path: Path, width: int = 320, height: int = 240, **overrides) -> str:
    data = {
        "camera": "test",
        "image_size": [width, height],
        "intrinsics": {"fx": 285.0, "fy": 285.0, "cx": 160.0, "cy": 120.0, "distortion": [0.0] * 5},
        "camera_to_world": [[1, 0, 0, 0.1], [0, 1, 0, 0.2], [0, 0, 1, 1.0], [0, 0, 0, 1]],
    }
    data.update(overrides)
    path.write_text(yaml.safe_dump(data))
    return str(path)


@pytest.fixture
def calibration_320(tmp_path):
    return write_calibration(tmp_path / "dummy.yaml")


def test_example_calibrations_load():
    for name in ("camera_left", "camera_right"):
        calibration = load_calibration(str(LAUNCH / "calibration" / f"{name}.yaml"))
        assert (calibration.intrinsics.width, calibration.intrinsics.height) == (512, 424)
        assert calibration.camera_to_world.shape == (4, 4)


def test_calibration_errors(tmp_path):
    with pytest.raises(DepthCameraError, match="does not exist"):
        load_calibration(str(tmp_path / "none.yaml"))
    skewed = write_calibration(
        tmp_path / "skewed.yaml", camera_to_world=[[2, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]]
    )
    with pytest.raises(DepthCameraError, match="not a rigid transform"):
        load_calibration(skewed)
    (tmp_path / "broken.yaml").write_text("image_size: [512]\n")
    with pytest.raises(DepthCameraError, match="broken.yaml is malformed"):
        load_calibration(str(tmp_path / "broken.yaml"))


def test_depth_image_carries_calibration_and_checks_size(calibration_320):
    calibration = load_calibration(calibration_320)
    depth = np.full((240, 320), 750, np.uint16)
    depth[0, 0] = 0
    image = depth_image(depth, calibration, "left", seq=4)
    assert image.header.frame_id == "camera_left" and image.header.seq == 4
    assert image.camera_to_world[:3, 3].tolist() == [0.1, 0.2, 1.0]
    metres = image.depth_m()
    assert np.isnan(metres[0, 0]) and metres[1, 1] == pytest.approx(0.75)
    with pytest.raises(DepthCameraError, match="sends 512x424 frames but its calibration is for 320x240"):
        depth_image(np.zeros((424, 512), np.uint16), calibration, "left", seq=1)


@needs_openni2
def test_streams_from_a_real_openni2_driver(calibration_320):
    camera = make_backend(
        {
            "backend": "openni2",
            "uri": "Dummy",
            "width": 320,
            "height": 240,
            "calibration_file": calibration_320,
            "name": "right",
        }
    )
    camera.connect()
    try:
        frames = [camera.read() for _ in range(3)]
    finally:
        camera.disconnect()
    assert [f.header.seq for f in frames] == [1, 2, 3]
    for frame in frames:
        assert frame.depth.shape == (240, 320) and frame.depth.dtype == np.uint16
        assert frame.header.frame_id == "camera_right"
        assert frame.intrinsics.fx == 285.0
    assert frames[0].depth.max() > 0


@needs_openni2
def test_depth_mode_not_offered_lists_modes(calibration_320):
    camera = make_backend({"backend": "openni2", "uri": "Dummy", "calibration_file": calibration_320})
    with pytest.raises(
        DepthCameraError,
        match=r"no depth mode 512x424@30 in millimetres; it offers: "
        r"\['320x240@30 ONI_PIXEL_FORMAT_DEPTH_1_MM'\]",
    ):
        camera.connect()


@needs_openni2
def test_calibration_for_another_resolution(tmp_path):
    wrong = write_calibration(tmp_path / "kinect.yaml", width=512, height=424)
    camera = make_backend(
        {"backend": "openni2", "uri": "Dummy", "width": 320, "height": 240, "calibration_file": wrong}
    )
    with pytest.raises(DepthCameraError, match="calibration .* is for 512x424"):
        camera.connect()


@needs_openni2
def test_no_kinect_says_what_to_connect_and_install(calibration_320):
    camera = make_backend({"backend": "openni2", "serial": "011987650947", "calibration_file": calibration_320})
    with pytest.raises(
        DepthCameraError,
        match=r"no OpenNI2 depth camera with serial '011987650947' found.*"
        r"USB 3.*libfreenect2-openni2.so.*OpenNI2/Drivers holds",
    ):
        camera.connect()


@needs_openni2
def test_unopenable_uri(calibration_320):
    camera = make_backend(
        {"backend": "openni2", "uri": "freenect2://0?serial=011987650947", "calibration_file": calibration_320}
    )
    with pytest.raises(DepthCameraError, match=r"cannot open OpenNI2 device 'freenect2://0\?serial="):
        camera.connect()


def test_library_not_installed(tmp_path):
    with pytest.raises(DepthCameraError, match=r"OpenNI2 library not found in .*apt-get install libopenni2-0"):
        load_openni2(str(tmp_path))


@needs_openni2
def test_plays_back_a_real_recording(tmp_path, calibration_320):
    """Record the Dummy device with OpenNI2's own recorder, then open the .oni as a camera."""
    load_openni2(LIBRARY_DIR)
    recording = tmp_path / "dummy.oni"
    device = openni2.Device(b"Dummy")
    stream = device.create_depth_stream()
    stream.start()
    recorder = openni2.Recorder(str(recording).encode())
    recorder.attach(stream)
    recorder.start()
    for _ in range(5):
        stream.read_frame().close()
    recorder.stop()
    recorder.close()
    stream.stop()
    stream.close()
    time.sleep(0.1)  # the Dummy driver's frame thread must end before its device closes
    device.close()
    camera = make_backend({"backend": "openni2", "oni_file": str(recording), "calibration_file": calibration_320})
    camera.connect()
    camera.disconnect()
    with pytest.raises(DepthCameraError, match="recording .*missing.oni does not exist"):
        make_backend(
            {"backend": "openni2", "oni_file": str(tmp_path / "missing.oni"), "calibration_file": calibration_320}
        ).connect()


@pytest.mark.skipif(importlib.util.find_spec("pylibfreenect2") is not None, reason="pylibfreenect2 is installed here")
def test_freenect2_backend_without_its_binding(calibration_320):
    camera = make_backend({"backend": "freenect2", "calibration_file": calibration_320})
    with pytest.raises(DepthCameraError, match=r"needs pylibfreenect2.*build libfreenect2.*dtx\[freenect2\]"):
        camera.connect()


def test_backend_and_parameter_errors():
    with pytest.raises(
        ValueError, match=r"unknown backend 'realsense'; allowed: \['freenect2', 'openni2', 'simulated'\]"
    ):
        make_backend({"backend": "realsense"})
    with pytest.raises(ValueError, match=r"unknown parameter\(s\) \['device'\]"):
        make_backend({"backend": "openni2", "device": "x"})
    with pytest.raises(DepthCameraError, match="unknown pipeline 'vulkan'"):
        make_backend({"backend": "freenect2", "pipeline": "vulkan"})
