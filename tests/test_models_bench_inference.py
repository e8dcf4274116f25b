"""The inference benchmark produces the table the issue asks for."""
from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

from benchmarks.inference import add_arguments, run
from dataset.format import DatasetReader
from dataset.synth import write_synthetic_dataset
from models.data import select_records
from models.evaluate import predict
from models.networks import GeneratorConfig
from models.ssim import ssim_rgb
from models.train import TrainConfig, load_generator, train


def test_benchmark_rows_have_the_required_fields_and_fp32_eager_is_the_reference() -> None:
    parser = argparse.ArgumentParser()
    add_arguments(parser)
    args = parser.parse_args(["--widths", "8", "--precisions", "fp32", "int8", "--runtimes", "eager", "onnxrt",
                              "--batch", "4", "--seconds", "0.05", "--threads", "1"])
    rows = run(args)
    assert [(r["precision"], r["runtime"]) for r in rows] == [("fp32", "eager"), ("fp32", "onnxrt"),
                                                              ("int8", "onnxrt")]
    for row in rows:
        assert set(row) == {"width", "precision", "runtime", "ssim", "ssim_vs_fp32", "regions_per_s", "p50_ms"}
        assert row["ssim"] == row["ssim_vs_fp32"]  # no dataset: the fp32 eager output is the reference
        assert row["width"] == 8 and row["regions_per_s"] > 0 and row["p50_ms"] > 0
    assert rows[0]["ssim"] == 1.0 and rows[1]["ssim"] > 0.99  # ONNX Runtime computes the same function


def test_with_a_dataset_ssim_is_against_the_test_splits_ground_truth(tmp_path: Path) -> None:
    """Trained checkpoints of two widths on a dataset: each row's SSIM is the paper's, against
    the test split's tactile images, and the rows within 0.01 of the best are marked."""
    write_synthetic_dataset(tmp_path / "ds", 40, seed=2, progress=False)
    checkpoints = []
    for width in (4, 8):
        config = TrainConfig(epochs=1, epochs_decay=0, batch_size=8, ndf=4, threads=1, max_steps=2,
                             generator=GeneratorConfig(ngf=width))
        checkpoints.append(str(train(tmp_path / "ds", config, tmp_path / f"w{width}", progress=False)))
    parser = argparse.ArgumentParser()
    add_arguments(parser)
    argv = ["--precisions", "fp32", "--runtimes", "eager", "--batch", "4", "--seconds", "0.05", "--threads", "1",
            "--dataset", str(tmp_path / "ds")]
    rows = run(parser.parse_args(argv + [a for c in checkpoints for a in ("--checkpoint", c)]))
    assert [r["width"] for r in rows] == [4, 8]
    reader = DatasetReader(tmp_path / "ds")
    test = [reader.load(r) for r in select_records(reader, "test")]
    truth = np.stack([s.tactile_rgb for s in test])
    for row, checkpoint in zip(rows, checkpoints):
        generator, depth_range_m = load_generator(checkpoint)
        estimate = predict(generator, np.stack([s.depth_map_m for s in test]), depth_range_m)
        assert row["ssim"] == round(float(ssim_rgb(truth, estimate).mean()), 4)
        assert row["ssim_vs_fp32"] == 1.0
    best = max(r["ssim"] for r in rows)
    assert [r["near_best"] for r in rows] == [r["ssim"] >= best - 0.01 for r in rows] and any(r["near_best"] for r in rows)
