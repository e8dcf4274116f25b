"""The report's sweeps on what a checkpoint serves (report.sweeps.serving) and the width table's
floor, the prior alone (report.sweeps.learned.width), on a tiny workspace: a contact library
standing in for the collected session, every model trained for one step and served as ``dtx
train`` serves it."""

from __future__ import annotations

import dataclasses
import math
import shutil
from pathlib import Path

import numpy as np
import pytest
import torch

from dataset.contact_library import write_contact_library
from dataset.reader import DatasetReader
from models.checkpoint import TrainConfig, load_generator
from models.data import network_input, select_records, to_uint8_rgb
from models.evaluate import contact_ssim
from models.serving import predict_served, served_images
from models.uncertainty import UNCERTAINTY_ABSENT, served_uncertainty_statistics
from perception.ssim import ssim_rgb
from report.plan import QUICK
from report.sweeps.learned import width
from report.sweeps.serving import serving, serving_as, uncertainty
from report.workspace import REFERENCE_SIZE, Workspace
from report.write import annotate

REPO = Path(__file__).resolve().parent.parent
TINY = dataclasses.replace(
    QUICK, samples=20, library_samples=8, epochs=1, trained_widths=(8,), dropout_samples=(2,), seed=0
)


class TinyWorkspace(Workspace):
    """The report's workspace with every training cut to one step of a small discriminator."""

    def config(self, size: int, width: int, registered: bool) -> TrainConfig:
        return dataclasses.replace(super().config(size, width, registered), max_steps=1, batch_size=8, ndf=8)


@pytest.fixture(scope="module")
def workspace(tmp_path_factory: pytest.TempPathFactory) -> TinyWorkspace:
    tmp = tmp_path_factory.mktemp("serving_sweeps")
    session = write_contact_library(tmp / "session", 40, seed=3, scene=REPO / "scenes" / "ycb_three.yaml").root
    ws = TinyWorkspace(tmp / "work", TINY, [session])
    ws.session_model()
    return ws


def _session_depth(ws: Workspace) -> np.ndarray:
    reader = DatasetReader(ws.session)
    return np.stack([reader.load(r.sample_id).depth_map_m for r in ws.session_test.records])


def test_the_learned_row_is_the_served_uncertaintys_own_statistics(workspace: TinyWorkspace) -> None:
    points = {p["setting"]: p for p in uncertainty(workspace)}
    assert set(points) == {"learned (served)", "dropout 2 samples"}
    generator, depth_range = load_generator(workspace.session_model() / "checkpoint.pt")
    images, levels = predict_served(generator, _session_depth(workspace), depth_range)
    truth = workspace.session_test.truth
    figures = served_uncertainty_statistics(levels, images, truth, 1.0 - ssim_rgb(truth, images))
    learned = points["learned (served)"]
    assert learned["accuracy"] == pytest.approx(figures["pearson_pixel"])
    assert learned["region_r"] == pytest.approx(figures["pearson_region"], abs=1e-4)
    assert learned["decile_ratio_min"] == pytest.approx(figures["decile_ratio_min"], abs=1e-3)
    assert learned["decile_ratio_max"] == pytest.approx(figures["decile_ratio_max"], abs=1e-3)
    assert learned["u_mean_levels"] == pytest.approx(figures["u_mean_levels"], abs=1e-3)
    # Dropout still samples in the sampling copy: a spread, scored the same way.
    assert points["dropout 2 samples"]["u_mean_levels"] > 0
    assert all(math.isfinite(p["time"]) and math.isfinite(p["estimate_ms"]) for p in points.values())


def test_the_serving_sweep_has_each_form_and_marks_the_one_served(workspace: TinyWorkspace) -> None:
    points = {p["setting"]: p for p in serving(workspace)}
    forms = ("prior alone", "network")
    assert set(points) == {f"{f} {w} uncertainty" for f in forms for w in ("with", "without")}
    generator, depth_range = load_generator(workspace.session_model() / "checkpoint.pt")
    served = [s for s, p in points.items() if p["served"]]
    assert served == [f"{dict(zip(('prior', 'network'), forms))[generator.serves]} with uncertainty"]
    # The prior alone is the prior's image as the generator draws it, with the uncertainty or without.
    test = workspace.session_test
    x = network_input(_session_depth(workspace), depth_range, generator.config, generator.prior)
    prior = to_uint8_rgb(served_images(generator, x, "prior"))
    expected = contact_ssim(test.truth, test.deformation, prior).mean()
    for setting in ("prior alone with uncertainty", "prior alone without uncertainty"):
        assert points[setting]["accuracy"] == pytest.approx(expected)
    assert all(p["regions_per_s"] > 0 and "refused" not in p for p in points.values())


def test_a_checkpoint_without_uncertainty_is_refused_with_the_reason_not_scored_as_zeros(
    workspace: TinyWorkspace, tmp_path: Path
) -> None:
    root = tmp_path / "work"
    shutil.copytree(workspace.root, root, ignore=shutil.ignore_patterns("data_*", "train_100_*"))
    checkpoint = root / f"train_session_{REFERENCE_SIZE}" / "checkpoint.pt"
    state = torch.load(checkpoint, weights_only=True)
    del state["uncertainty"]  # as a checkpoint that serves what it chose, trained before the uncertainty
    torch.save(state, checkpoint)
    before = TinyWorkspace(root, TINY, workspace.sessions)
    learned = next(p for p in uncertainty(before) if p["setting"] == "learned (served)")
    assert math.isnan(learned["accuracy"]) and learned["refused"] == UNCERTAINTY_ABSENT
    assert not any(k in learned for k in ("region_r", "u_mean_levels"))
    forms = serving(before)
    refused = [p for p in forms if "refused" in p]
    assert {p["setting"] for p in refused} == {"prior alone with uncertainty", "network with uncertainty"}
    assert all(math.isnan(p["accuracy"]) and not p["served"] for p in refused)
    assert [p["setting"] for p in forms if p["served"]] == [
        f"{'prior alone' if state['serves'] == 'prior' else 'network'} without uncertainty"
    ]
    # A refused form is no option: never on the front, never advised.
    assert not any(p["pareto"] or p["recommended"] for p in annotate(forms) if "refused" in p)


def test_serving_as_restores_what_the_checkpoint_serves(workspace: TinyWorkspace) -> None:
    generator, _ = load_generator(workspace.session_model() / "checkpoint.pt")
    saved = generator.serves, generator.uncertainty
    with pytest.raises(RuntimeError), serving_as(generator, "prior", None):
        assert generator.serves == "prior" and generator.uncertainty is None
        raise RuntimeError("a sweep that fails half-way")
    assert (generator.serves, generator.uncertainty) == saved


def test_the_width_table_goes_down_to_the_prior_alone(workspace: TinyWorkspace) -> None:
    points = {p["setting"]: p for p in width(workspace)}
    assert set(points) == {"width 8", "prior alone"}
    prior = points["prior alone"]
    assert prior["parameters"] == 0 and points["width 8"]["parameters"] > 0
    generator, depth_range = load_generator(workspace.model(REFERENCE_SIZE, 8) / "checkpoint.pt")
    reader = DatasetReader(workspace.dataset(REFERENCE_SIZE))
    depth = np.stack([reader.load(r).depth_map_m for r in select_records(reader, "test")])
    x = network_input(depth, depth_range, generator.config, generator.prior)
    _, truth = workspace.test
    expected = ssim_rgb(truth, to_uint8_rgb(served_images(generator, x, "prior"))).mean()
    assert prior["accuracy"] == pytest.approx(expected)
    # The width rows are the network's estimates, whatever the checkpoint chose to serve.
    network = ssim_rgb(truth, to_uint8_rgb(served_images(generator, x, "network"))).mean()
    assert points["width 8"]["accuracy"] == pytest.approx(network)
