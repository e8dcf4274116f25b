"""``dtx bench train``: one session and several trained side by side in one run, each as
``dtx train`` runs, with its peak memory and epoch time."""

from __future__ import annotations

import argparse
from pathlib import Path

import pytest

from benchmarks import train as bench_train

CONFIG = (
    "epochs: 3\nepochs_decay: 2\nbatch_size: 4\nndf: 8\nthreads: 1\nsession_pose_sigma_mm: 1.0\n"
    "generator: {ngf: 8, prior: true, background: false}\n"
)


def _args(tmp_path: Path, **changes: object) -> argparse.Namespace:
    parser = argparse.ArgumentParser()
    bench_train.add_arguments(parser)
    config = tmp_path / "tiny.yaml"
    config.write_text(CONFIG)
    args = parser.parse_args(
        ["--synth", "2", "--pairs", "24", "--work", str(tmp_path / "work"), "--config", str(config)]
    )
    return argparse.Namespace(**{**vars(args), **changes})


def test_one_session_and_all_of_them_are_measured_side_by_side(tmp_path: Path) -> None:
    rows = bench_train.run(_args(tmp_path, pair_cache_mib=1.0))
    one, both = rows
    assert (one["sessions"], one["pairs"], both["sessions"], both["pairs"]) == (1, 24, 2, 48)
    assert 0 < one["train_pairs"] < both["train_pairs"] < 48
    assert both["steps"] == -(-both["train_pairs"] // 4)  # one whole epoch, not the config's five
    assert both["pairs_trained"] == both["train_pairs"] and both["ms_per_pair"] > 0
    for row in rows:
        assert row["peak_mib"] > 100 and row["epoch_s"] > 0 and row["cpu_s"] > 0 and row["pair_cache_mib"] == 1.0
    assert one["peak_over_one_mib"] == 0 and both["peak_over_one_mib"] == round(both["peak_mib"] - one["peak_mib"], 1)
    assert sorted(p.name for p in (tmp_path / "work").iterdir()) == ["session00", "session01"]  # kept for next time
    cut = bench_train.run(_args(tmp_path, pair_cache_mib=1.0, max_steps=1))[1]  # the sessions made above
    assert (cut["steps"], cut["pairs_trained"], cut["train_pairs"]) == (1, 4, both["train_pairs"])


def test_a_failing_run_says_why_and_a_bad_cache_is_refused_before_any_run(tmp_path: Path) -> None:
    with pytest.raises(Exception, match="pair_cache_mib must be a finite number"):
        bench_train.run(_args(tmp_path, pair_cache_mib=-1.0))
    assert not (tmp_path / "work").exists()  # nothing synthesised for a run that cannot start
    with pytest.raises(SystemExit, match=r"dtx train on 1 sessions failed \(exit 1\):\n.*missing"):
        bench_train.run(_args(tmp_path, session=[str(tmp_path / "missing")]))
