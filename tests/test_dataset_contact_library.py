"""The contact library: pairs made in a session's geometry, reproducible, resumable, and each
depth-map showing its contact where its image does."""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np
import pytest
from scipy import ndimage

from dataset.check import check_dataset
from dataset.cli import add_commands
from dataset.contact_library import FAMILIES, library_sample, random_surface_mm, write_contact_library
from dataset.images import resize_rgb
from dataset.reader import DatasetReader
from dataset.records import DatasetError
from perception.depthmap import DepthMapParams
from sim.gelsight import scene_renderer
from workcell.scene import load_scene

SCENE = Path(__file__).resolve().parent.parent / "scenes" / "ycb_three.yaml"


def test_the_library_is_reproducible_resumable_and_a_sound_dataset(tmp_path: Path) -> None:
    write_contact_library(tmp_path / "a", 14, seed=4, scene=SCENE)
    write_contact_library(tmp_path / "b", 5, seed=4, scene=SCENE)
    write_contact_library(tmp_path / "b", 14, seed=4, scene=SCENE)
    a, b = DatasetReader(tmp_path / "a"), DatasetReader(tmp_path / "b")
    assert [r.sha256 for r in a.records] == [r.sha256 for r in b.records] and len(a) == 14
    assert {r.object_name for r in a.records} == set(FAMILIES)
    assert a.info.depth_range_m == (-0.005, 0.01) and a.info.depth_crop_m is not None
    assert check_dataset(tmp_path / "a").ok


@pytest.mark.parametrize("family", FAMILIES)
def test_a_pressed_depth_map_shows_its_contact_where_the_image_does(family: str) -> None:
    scene = load_scene(SCENE)
    renderer = scene_renderer(scene, effects=False)
    background = resize_rgb(renderer.background(), 100, 100).astype(float)
    geometry = scene.gripper_geometry()
    params = DepthMapParams(shape=(100, 100), margin_m=0.002, y_range_m=(-0.005, 0.01))
    # The depth-map covers the sensed area plus the margin; the image, the sensed area alone.
    sensed_x, sensed_z = geometry.sensed_extent_m
    cols = (np.arange(100) + 0.5) / 100 * (sensed_x + 0.004) - (sensed_x / 2 + 0.002)
    rows = (np.arange(100) + 0.5) / 100 * (sensed_z + 0.004) - (sensed_z / 2 + 0.002)
    in_view = (np.abs(rows)[:, None] < sensed_z / 2) & (np.abs(cols)[None, :] < sensed_x / 2)
    checked = 0
    for seed in range(40):
        pair = library_sample(family, np.random.default_rng(seed), geometry, params, renderer, (100, 100))
        if pair is None:
            continue
        depth_map, image, _ = pair
        pressed = (depth_map < -0.0003) & in_view
        # Nothing within 1 mm of the gel, and 2 mm (8 bins) from anything that is: the gel's
        # spread and a face's edge colour the image around a contact.
        clear = ~ndimage.binary_dilation(depth_map < 0.001, iterations=8) & in_view
        if pressed.sum() < 20 or clear.sum() < 20:
            continue
        change = np.abs(image.astype(float) - background).sum(axis=2)
        # The image shows the sensed area on its 100 x 100 grid: where each depth-map bin is there.
        r = np.broadcast_to(((rows[:, None] + sensed_z / 2) / sensed_z * 100).astype(int).clip(0, 99), pressed.shape)
        c = np.broadcast_to(((cols[None, :] + sensed_x / 2) / sensed_x * 100).astype(int).clip(0, 99), pressed.shape)
        assert change[r[pressed], c[pressed]].mean() > 3 * change[r[clear], c[clear]].mean() + 5, f"{family} {seed}"
        checked += 1
    assert checked >= 3


def test_an_unknown_family_and_a_bad_count_are_refused(tmp_path: Path) -> None:
    with pytest.raises(DatasetError, match="unknown contact family"):
        random_surface_mm("torus", np.random.default_rng(0))
    with pytest.raises(DatasetError, match="must be positive"):
        write_contact_library(tmp_path / "x", 0, seed=0, scene=SCENE)


@pytest.mark.parametrize("depth_range", [["0.01", "-0.005"], ["nan", "0.01"]])
def test_the_command_refuses_a_bad_depth_range_and_writes_nothing(
    tmp_path: Path, depth_range: list[str], capsys: pytest.CaptureFixture
) -> None:
    parser = argparse.ArgumentParser()
    add_commands(parser.add_subparsers())
    args = parser.parse_args(
        ["dataset", "library", str(tmp_path / "lib"), "--samples", "2", "--depth-range-m", *depth_range]
    )
    assert args.func(args) == 2
    assert "error:" in capsys.readouterr().err and not (tmp_path / "lib").exists()


def test_each_contact_records_where_the_gel_was_on_its_shape_so_two_libraries_are_not_all_twins(
    tmp_path: Path,
) -> None:
    """A library's contacts are drawn shapes, not one object at the world's origin: each records
    its shape's place in the gel frame (model_to_gel), and the twin rule across sessions joins
    only contacts at the same place on a shape of the same family."""
    from dataset.splits import twin_grasps

    first, second = (write_contact_library(tmp_path / f"lib{seed}", 40, seed=seed, scene=SCENE) for seed in (0, 1))
    poses = np.array([r.model_to_gel for r in first.records])
    assert poses.shape == (40, 4, 4) and np.allclose(poses[:, :3, :3], np.eye(3))
    assert len({tuple(p[:3, 3].round(6)) for p in poses}) == 40  # every contact somewhere else
    twins = twin_grasps([first.records, second.records])
    assert len(twins) < 10  # every contact at the one origin, as before: 268 pairs of 40 and 40
