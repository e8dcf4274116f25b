"""``dtx report accuracy-time --session A B``: the session sweeps' model trained on every given
session, scored on their test splits together and on each one's, the per-session column only
where there are several, and the sessions named by what they hold."""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import numpy as np
import pytest
from test_report_cli import _parser
from test_report_serving_sweeps import TINY, TinyWorkspace

from dataset.contact_library import write_contact_library
from dataset.reader import DatasetReader
from dataset.splits import session_fingerprint
from models.checkpoint import load_checkpoint, load_generator
from models.data import select_records
from models.evaluate import contact_ssim, contact_windows
from models.serving import predict
from models.sessions import checkpoint_sessions
from report.plan import QUICK
from report.specs import PER_SESSION, SPECS
from report.sweeps.session import pose_sigma
from report.workspace import Workspace, training_config
from report.write import annotate, table

REPO = Path(__file__).resolve().parent.parent
PLAN = dataclasses.replace(TINY, pose_sigmas_mm=(0.0,))


@pytest.fixture(scope="module")
def sessions(tmp_path_factory: pytest.TempPathFactory) -> list[Path]:
    """Two sessions of one GelSight with other objects (as make demo's and scenes/ycb_unseen.yaml's)."""
    tmp = tmp_path_factory.mktemp("report_sessions")
    return [
        write_contact_library(tmp / "three", 40, seed=3, scene=REPO / "scenes" / "ycb_three.yaml").root,
        write_contact_library(tmp / "unseen", 40, seed=4, scene=REPO / "scenes" / "ycb_unseen.yaml").root,
    ]


@pytest.fixture(scope="module")
def workspace(sessions: list[Path], tmp_path_factory: pytest.TempPathFactory) -> TinyWorkspace:
    ws = TinyWorkspace(tmp_path_factory.mktemp("work"), PLAN, sessions)
    ws.session_model()
    return ws


def test_the_test_split_is_each_sessions_in_order(workspace: TinyWorkspace, sessions: list[Path]) -> None:
    test = workspace.session_test
    for index, session in enumerate(sessions):
        reader = DatasetReader(session)
        records = select_records(reader, "test")
        part = test.part(index)
        assert [r.sample_id for r in part.records] == [r.sample_id for r in records]
        assert np.array_equal(part.truth, np.stack([reader.load(r).tactile_rgb for r in records]))
        maps = part.depth_maps(workspace.sessions)
        assert np.array_equal(maps, np.stack([reader.load(r).depth_map_m for r in records]))
    assert len(test.records) == sum(len(test.part(i).records) for i in range(len(sessions)))
    assert workspace.session == sessions[0] and workspace.first_test.records == test.part(0).records


def test_the_session_model_learns_from_every_session(workspace: TinyWorkspace, sessions: list[Path]) -> None:
    checkpoint = load_checkpoint(workspace.session_model() / "checkpoint.pt")
    assert checkpoint_sessions(checkpoint) == [str(s) for s in sessions]


def test_each_sessions_contact_ssim_is_its_own_test_splits(workspace: TinyWorkspace) -> None:
    row = next(p for p in pose_sigma(workspace) if p["setting"] == "0 mm")
    generator, depth_range = load_generator(workspace.session_model() / "checkpoint.pt")
    expected = []
    for index in range(2):
        part = workspace.session_test.part(index)
        estimate = predict(generator, part.depth_maps(workspace.sessions), depth_range, pose_sigma_mm=0.0)
        expected.append(contact_ssim(part.truth, part.deformation, estimate).mean())
    assert [float(v) for v in row[PER_SESSION].split(" / ")] == pytest.approx(expected, abs=1e-4)
    assert row["contact_pairs"] == len(contact_windows(workspace.session_test.deformation)[0])  # both sessions'
    assert "contact SSIM per session" in table(SPECS["pose_sigma"], annotate([row]))
    alone = {key: value for key, value in row.items() if key != PER_SESSION}
    assert "contact SSIM per session" not in table(SPECS["pose_sigma"], annotate([alone]))


def _report(out: Path, sessions: list[Path], *more: str) -> int:
    """``dtx report accuracy-time --quick --reuse --only density --session ...`` into ``out``."""
    command = ["report", "accuracy-time", "--out", str(out), "--quick", "--reuse", "--only", "density", *more]
    args = _parser().parse_args([*command, "--session", *map(str, sessions)])
    return args.func(args)


def test_the_same_session_twice_is_refused(
    sessions: list[Path], tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    (tmp_path / "cache").mkdir()
    assert _report(tmp_path, [sessions[0], sessions[0]]) == 2
    assert "the same session given twice" in capsys.readouterr().err
    assert not (tmp_path / "work").exists()


def test_several_sessions_are_named_by_what_they_hold(sessions: list[Path], tmp_path: Path) -> None:
    """A cached sweep of the same sessions in the same order is reused, the report says which
    sessions it ran on, and a text with their paths in it names them as SESSION1, SESSION2."""
    out = tmp_path / "report"
    (out / "cache").mkdir(parents=True)
    made_by = {"plan": dataclasses.asdict(QUICK), "training_config": training_config().to_dict()}
    refusal = f"{sessions[1].resolve()} and {sessions[0].resolve()}"
    points = [{"sweep": "density", "setting": "unfiltered", "time": 1.0, "accuracy": 0.8, "refused": refusal}]
    entry = {**made_by, "session": "+".join(session_fingerprint(s) for s in sessions), "seconds": 1.0}
    (out / "cache" / "density.json").write_text(json.dumps({**entry, "measured_at": "then", "points": points}))
    assert _report(out, sessions) == 0
    written = (out / "report.md").read_text() + (out / "points.json").read_text()
    assert "density reused" in written and "2 collected sessions" in written
    assert "SESSION2 and SESSION1" in written and str(tmp_path) not in written


def test_the_given_sessions_pose_errors_reach_their_models_and_the_cache(sessions: list[Path], tmp_path: Path) -> None:
    workspace = Workspace(tmp_path, QUICK, sessions, (0.1, 1.0))
    config = workspace.config(100, 16, registered=True)
    assert config.session_pose_sigma_mm == 0.1 and config.session_pose_sigmas_mm == (0.1, 1.0)
    assert workspace.config(100, 16, registered=False).session_pose_sigma_mm == 0.0  # analytic contacts: exact
    out = tmp_path / "report"
    (out / "cache").mkdir(parents=True)
    made_by = {"plan": dataclasses.asdict(QUICK), "training_config": training_config().to_dict()}
    entry = {**made_by, "session": "+".join(session_fingerprint(s) for s in sessions), "seconds": 1.0}
    entry |= {"session_pose_sigmas_mm": [0.1, 1.0], "measured_at": "then", "points": []}
    (out / "cache" / "density.json").write_text(json.dumps(entry))
    assert _report(out, sessions, "--session-pose-sigma-mm", "0.1", "1") == 0
    written = (out / "report.md").read_text()
    assert "density reused" in written and "told pose errors of 0.1 / 1 mm" in written


@pytest.mark.parametrize(
    ("given", "sigmas", "says"),
    [
        (0, ["0.1"], "for given sessions"),
        (2, ["0.1", "0.2", "0.3"], "one value or one a session (2), got 3"),
        (2, ["-1"], "session_pose_sigma_mm"),
        (2, ["nan"], "session_pose_sigma_mm"),
    ],
)
def test_pose_errors_that_do_not_fit_the_sessions_are_refused_before_any_work(
    sessions: list[Path], tmp_path: Path, capsys: pytest.CaptureFixture[str], given: int, sigmas: list[str], says: str
) -> None:
    command = ["report", "accuracy-time", "--out", str(tmp_path), "--quick", "--session-pose-sigma-mm", *sigmas]
    args = _parser().parse_args(command + (["--session", *map(str, sessions[:given])] if given else []))
    assert args.func(args) == 2
    assert says in capsys.readouterr().err
    assert not (tmp_path / "work").exists() and not (tmp_path / "cache").exists()


def test_a_model_is_reused_only_when_an_earlier_run_trained_it(workspace: TinyWorkspace) -> None:
    """The header lists models an earlier run trained (their training is not in its times): not
    one this run trained and a later sweep asks for again."""
    workspace.session_model()
    assert workspace.reused_models == set()
    later = TinyWorkspace(workspace.root, workspace.plan, workspace.sessions)
    later.session_model()
    assert later.reused_models == {workspace.session_model().name}
