"""Training for the pose uncertainties a planner will ask about (``library_pose_sigma_range_mm``):
library pairs moved as a registration that far off would have cut them, their prior rendered at
that uncertainty; seeded, validated, recorded in the checkpoint."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import torch

from dataset.contact_library import write_contact_library
from dataset.reader import DatasetReader
from models.checkpoint import TrainConfig, load_checkpoint, load_generator
from models.data import moved_in_gel_plane, session_prior
from models.networks import GeneratorConfig, ModelConfigError
from models.pairs import PairCache, PairSet, library_pairs
from models.train import train
from perception.normalisation import denormalise_depth_map

REPO = Path(__file__).resolve().parent.parent
SCENE = str(REPO / "scenes" / "ycb_three.yaml")
PRIOR = GeneratorConfig(ngf=8, prior=True, background=False)
TINY = TrainConfig(epochs=1, epochs_decay=1, batch_size=8, ndf=8, threads=1, max_steps=1, generator=PRIOR)


@pytest.fixture(scope="module")
def library(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return write_contact_library(tmp_path_factory.mktemp("sigma") / "library", 24, seed=2, scene=SCENE).root


def test_a_map_moves_by_whole_bins_of_its_crop_and_what_leaves_the_crop_is_gone() -> None:
    crop_m, y_far = (0.010, 0.004, 0.005), 0.0025  # 10 columns of 1 mm, 5 rows of 1 mm
    maps = np.full((3, 5, 10), y_far, np.float32)
    maps[:, 2, 4] = -0.001
    moved = moved_in_gel_plane(maps, np.array([[0.0, 0.0], [2.2, -0.9], [40.0, 0.0]]), crop_m, y_far)
    np.testing.assert_array_equal(moved[0], maps[0])
    assert np.argwhere(moved[1] < y_far).tolist() == [[1, 6]]  # x +2 mm -> 2 columns, z -1 mm -> 1 row
    assert (moved[2] == y_far).all()  # beyond the crop: no surface left
    assert moved.dtype == maps.dtype and (maps[:, 2, 4] == -0.001).all()  # the input is untouched


def _library_inputs(library: Path, sigma_range_mm: tuple[float, ...], seed: int = 0) -> torch.Tensor:
    reader = DatasetReader(library)
    sources = library_pairs([library], [reader], PRIOR, session_prior(reader, PRIOR), sigma_range_mm, seed)
    return PairSet(sources, PRIOR.in_channels, PairCache(0)).tensors()[0]


def _shift_bins(
    exact: np.ndarray, moved: np.ndarray, crop_m: tuple[float, float, float], reach: int = 16
) -> list[tuple[int, int]]:
    """Every whole-bin shift (columns, rows) within ``reach`` that turns the normalised map
    ``exact`` into ``moved`` (+1: no surface)."""
    pitch_mm = 1e3 * np.array([crop_m[0], crop_m[2]]) / np.array(exact.shape[::-1])
    shifts = [(c, r) for r in range(-reach, reach + 1) for c in range(-reach, reach + 1)]
    return [
        shift
        for shift in shifts
        if np.array_equal(moved_in_gel_plane(exact[None], np.array([shift]) * pitch_mm, crop_m, 1.0)[0], moved)
    ]


def test_the_library_is_shown_as_registered_that_far_off_with_the_uncertainty_it_claims(library: Path) -> None:
    exact = _library_inputs(library, ())
    assert torch.equal(_library_inputs(library, (0.0, 0.0)), exact)  # zero uncertainty: the exact pairs
    unsure = _library_inputs(library, (1.0, 1.0))
    assert torch.equal(_library_inputs(library, (1.0, 1.0)), unsure)  # seeded
    assert not torch.equal(_library_inputs(library, (1.0, 1.0), seed=1), unsure)
    # Each depth-map is its exact one moved by whole bins, by a Gaussian offset of 1 mm.
    reader = DatasetReader(library)
    crop = reader.info.depth_crop_m
    assert crop is not None
    crop_m = (float(crop[0]), float(crop[1]), float(crop[2]))
    shifts = [_shift_bins(e.numpy(), u.numpy(), crop_m) for e, u in zip(exact[:, 0], unsure[:, 0])]
    assert all(len(found) == 1 for found in shifts), shifts
    offsets_mm = np.array([found[0] for found in shifts]) * 1e3 * np.array([crop_m[0], crop_m[2]]) / 100
    assert 0.7 < np.sqrt(np.mean(offsets_mm**2)) < 1.4  # 24 pairs x 2 axes, each rounded to a bin (0.24 / 0.19 mm)
    # Each pair's prior is the 1 mm image of its moved depth-map (read back from the depth channel).
    prior = session_prior(reader, PRIOR)
    assert prior is not None
    moved = denormalise_depth_map(unsure[:, 0].numpy(), reader.info.depth_range_m)
    expected = prior.channels(moved, 1.0)
    assert (unsure[:, 1:] - expected).abs().max() <= 2 / 127.5  # float32 metres, read back
    assert (exact[:, 1:] - expected).abs().max() > 0.2  # not the exact pairs' sharp image


def test_a_checkpoint_records_the_range_it_was_trained_for(library: Path, tmp_path: Path) -> None:
    config = TrainConfig(**{**TINY.__dict__, "library_pose_sigma_range_mm": (0.0, 1.5)})
    path = train(library, config, tmp_path / "run", progress=False, libraries=[library])
    assert TrainConfig.from_dict(load_checkpoint(path)["train_config"]).library_pose_sigma_range_mm == (0.0, 1.5)
    generator, _ = load_generator(path)
    assert generator.prior is not None and generator.prior.spec.pose_sigma_mm == 0.0  # the default stays the session's
    exact = load_checkpoint(train(library, TINY, tmp_path / "exact", progress=False, libraries=[library]))
    trained = load_checkpoint(path)
    assert not all(
        torch.equal(trained["generator"][k], v) for k, v in exact["generator"].items()
    )  # it learnt from them


@pytest.mark.parametrize(
    ("sigma_range", "generator", "message"),
    [
        ((0.5,), PRIOR, r"\[low, high\]"),
        ((0.0, 1.0, 2.0), PRIOR, r"\[low, high\]"),
        ((1.0, 0.5), PRIOR, "low <= high"),
        ((0.0, 6.0), PRIOR, r"library_pose_sigma_range_mm must be a finite number of mm in \[0, 5\]"),
        ((-1.0, 1.0), PRIOR, "library_pose_sigma_range_mm must be a finite number"),
        ((0.0, float("nan")), PRIOR, "library_pose_sigma_range_mm must be a finite number"),
        ((0.0, 1.0), GeneratorConfig(ngf=8), "needs a generator with a physics prior"),
    ],
)
def test_a_bad_range_is_refused_naming_it(
    sigma_range: tuple[float, ...], generator: GeneratorConfig, message: str
) -> None:
    with pytest.raises(ModelConfigError, match=message):
        TrainConfig(library_pose_sigma_range_mm=sigma_range, generator=generator).validate()


def test_the_range_loads_from_a_config_file(tmp_path: Path) -> None:
    path = tmp_path / "config.yaml"
    path.write_text("library_pose_sigma_range_mm: [0, 1.5]\ngenerator: {prior: true}\n")
    assert TrainConfig.load(path).library_pose_sigma_range_mm == (0.0, 1.5)
    path.write_text("library_pose_sigma_range_mm: [0, one]\ngenerator: {prior: true}\n")
    with pytest.raises(ModelConfigError, match="library_pose_sigma_range_mm"):
        TrainConfig.load(path)
