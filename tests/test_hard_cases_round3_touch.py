"""Hard cases, round three (issue 52), touch calibration's joint fit: a cell fitted far from the
world origin recovers its cameras as well as one at the origin, and every malformed touch, SSD
cell, table cloud or depth-map shift is refused with ``TouchCalibrationError`` naming the
argument, never a silent NaN, a turn made up from a line, or a Python error.

The constructed cell: two cameras each see one side of two boxes, the boxes registered between
the cameras' two errors, and 60 touches a box on its sides with 0.05 mm noise (the cell of
tests/test_touch_calibration.py, self-contained here). Hypothesis runs derandomized."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from test_touch_calibration import _box_mesh, _box_model, _touches_on

from perception.touch_calibration import (
    TouchCalibrationError,
    TouchOffset,
    moved_depth_map,
    planar_transform,
    pose_error,
    profiled_fit,
    solve_cell,
    table_levelling,
)

pytestmark = pytest.mark.filterwarnings("error")  # a RuntimeWarning on the way fails the case

SIZES = {"a": (0.06, 0.04, 0.1), "b": (0.05, 0.08, 0.06)}
# Where the boxes stand in the cell's own frame (yaw rad, x mm, y mm).
PLACES = {"a": (0.3, -150.0, 20.0), "b": (-0.5, 160.0, -30.0)}
GRID = (np.arange(-1, 2) * 0.4, np.arange(-1, 2) * 0.4, np.arange(-1, 2) * 0.1)


def _cell(
    cell_to_world: np.ndarray, errors: dict[str, np.ndarray]
) -> tuple[dict[str, list[TouchOffset]], dict[str, np.ndarray], dict[str, dict[str, np.ndarray]]]:
    """Touches, registered poses and camera views of the constructed cell standing at
    ``cell_to_world``, each camera off by ``errors[c]`` (a turn and shift in the cell's frame):
    made in the cell's frame, noise and all, then carried into the world."""
    rng = np.random.default_rng(2)
    truth = {o: planar_transform(*PLACES[o]) for o in SIZES}
    # the registration, from both cameras' points, lands between their two errors
    half = [_halved(e) for e in errors.values()]
    predicted = {o: half[0] @ half[1] @ truth[o] for o in truth}
    models = {o: _box_model(size) for o, size in SIZES.items()}
    views: dict[str, dict[str, np.ndarray]] = {}
    for side, (camera, error) in zip((1, -1), errors.items()):
        views[camera] = {}
        for o in truth:
            seen = models[o][0][models[o][0][:, 1] * side < 0.01]
            in_cell = seen @ truth[o][:3, :3].T + truth[o][:3, 3]
            moved = in_cell @ error[:3, :3].T + error[:3, 3] + rng.normal(0, 0.0005, in_cell.shape)
            views[camera][o] = moved @ cell_to_world[:3, :3].T + cell_to_world[:3, 3]
    touches = {
        o: [
            TouchOffset(
                t.offset_gel_mm,
                t.information_gel,
                cell_to_world[:3, :3] @ t.contact_world_m + cell_to_world[:3, 3],
                cell_to_world @ t.gel_to_world,
            )
            for t in _touches_on(models[o], truth[o], predicted[o], rng)
        ]
        for o in truth
    }
    return touches, {o: cell_to_world @ pose for o, pose in predicted.items()}, views


def _halved(error: np.ndarray) -> np.ndarray:
    yaw = np.arctan2(error[1, 0], error[0, 0])
    return planar_transform(yaw / 2, *(error[:2, 3] * 1e3 / 2))


def _fitted_errors(cell_to_world: np.ndarray, errors: dict[str, np.ndarray]) -> dict[str, tuple[float, float]]:
    """(mm, degrees) each camera is left off after the joint fit of the cell at ``cell_to_world``,
    in the cell's frame (a turn left over, read at the world origin, would be a kilometre's lever)."""
    touches, predicted, views = _cell(cell_to_world, errors)
    cell = solve_cell(touches, predicted, views, {o: _box_mesh(size) for o, size in SIZES.items()})
    to_cell = np.linalg.inv(cell_to_world)
    return {
        camera: pose_error(to_cell @ cell.cameras[camera] @ cell_to_world @ error, np.eye(4))
        for camera, error in errors.items()
    }


@settings(max_examples=10, deadline=None, derandomize=True)
@given(
    st.floats(-1000.0, 1000.0),
    st.floats(-1000.0, 1000.0),
    st.floats(-np.pi, np.pi),
    st.floats(-0.08, 0.08),
    st.lists(st.floats(-2.0, 2.0), min_size=2, max_size=2),
)
def test_a_cell_anywhere_in_the_world_recovers_its_cameras_as_at_the_origin(
    x_m: float, y_m: float, yaw_rad: float, camera_deg: float, camera_mm: list[float]
) -> None:
    """A site or map frame puts the cell up to a kilometre from the world origin: the fit turns
    about the cell, so the cameras come out as well as with the cell at the origin."""
    errors = {
        "left": planar_transform(np.radians(camera_deg), *camera_mm),
        "right": planar_transform(np.radians(-0.05), 1.0, -0.5),
    }
    at_origin = _fitted_errors(np.eye(4), errors)
    far = _fitted_errors(planar_transform(yaw_rad, x_m * 1e3, y_m * 1e3), errors)
    for camera in errors:
        assert at_origin[camera][0] < 0.1 and at_origin[camera][1] < 0.015, (camera, at_origin)
        np.testing.assert_allclose(far[camera], at_origin[camera], atol=1e-4, err_msg=camera)


@pytest.mark.parametrize("distance_m", [30.0, 1000.0])
def test_the_probes_cell_far_away_keeps_no_turn(distance_m: float) -> None:
    """The probe's case: a 0.05 degree camera turn with the cell 30 m or 1 km out along x was
    left at 0.020 or 0.050 degrees (0.008 with the cell at the origin, its noise's share)."""
    errors = {"left": planar_transform(np.radians(0.05), 0.0, 0.0), "right": np.eye(4)}
    at_origin = _fitted_errors(np.eye(4), errors)
    far = _fitted_errors(planar_transform(0.0, distance_m * 1e3, 0.0), errors)
    assert far["left"][1] < 0.01 and far["left"][0] < 0.05, far
    for camera in errors:
        np.testing.assert_allclose(far[camera], at_origin[camera], atol=1e-4)


# -- a touch, the fit's other inputs ---------------------------------------------------------


def _touch(**change: object) -> TouchOffset:
    fields: dict[str, object] = {
        "offset_gel_mm": np.array([0.1, -0.2]),
        "information_gel": np.eye(2) * 400.0,
        "contact_world_m": np.array([0.1, 0.2, 0.05]),
        "gel_to_world": np.eye(4),
    }
    fields.update(change)
    return TouchOffset(**fields)  # type: ignore[arg-type]


@pytest.mark.parametrize(
    ("field", "value"),
    [
        ("offset_gel_mm", np.array([np.nan, 0.0])),
        ("offset_gel_mm", np.array([np.inf, 0.0])),
        ("offset_gel_mm", np.zeros(3)),
        ("information_gel", np.diag([np.inf, 1.0])),
        ("information_gel", np.diag([np.nan, 1.0])),
        ("information_gel", np.diag([-1.0, 1.0])),
        ("information_gel", np.array([[1.0, 0.5], [0.0, 1.0]])),
        ("information_gel", np.eye(3)),
        ("contact_world_m", np.array([0.0, np.nan, 0.0])),
        ("contact_world_m", np.zeros(2)),
        ("gel_to_world", np.full((4, 4), np.nan)),
        ("gel_to_world", np.eye(4) * 2.0),
        ("gel_to_world", np.eye(3)),
    ],
)
def test_a_malformed_touch_is_refused_by_field(field: str, value: np.ndarray) -> None:
    with pytest.raises(TouchCalibrationError, match=field):
        _touch(**{field: value})


def test_a_touch_cannot_be_changed_after_its_check() -> None:
    touch = _touch()
    with pytest.raises(ValueError, match="read-only"):
        touch.offset_gel_mm[0] = np.nan


def _small_cell() -> tuple[dict[str, list[TouchOffset]], dict[str, np.ndarray], dict[str, dict[str, np.ndarray]]]:
    return _cell(np.eye(4), {"left": np.eye(4), "right": np.eye(4)})


MESHES = {o: _box_mesh(size) for o, size in SIZES.items()}


@pytest.mark.parametrize("iterations", [0, -1, 2.5, True])
def test_a_fit_of_no_whole_iterations_is_refused(iterations: int) -> None:
    touches, predicted, views = _small_cell()
    with pytest.raises(TouchCalibrationError, match="iterations"):
        solve_cell(touches, predicted, views, MESHES, iterations=iterations)


def test_the_fits_other_inputs_are_refused_by_name() -> None:
    touches, predicted, views = _small_cell()
    with pytest.raises(TouchCalibrationError, match="predicted"):
        solve_cell(touches, {}, {}, MESHES)
    with pytest.raises(TouchCalibrationError, match=r"predicted\['a'\]"):
        solve_cell(touches, {**predicted, "a": np.full((4, 4), np.nan)}, views, MESHES)
    with pytest.raises(TouchCalibrationError, match="touches.*'c'"):
        solve_cell({**touches, "c": touches["a"]}, predicted, views, MESHES)
    with pytest.raises(TouchCalibrationError, match=r"touches\['a'\]\[1\]"):
        solve_cell({**touches, "a": [touches["a"][0], "not a touch"]}, predicted, views, MESHES)  # type: ignore[list-item]
    with pytest.raises(TouchCalibrationError, match=r"views\['left'\]\['a'\]"):
        solve_cell(touches, predicted, {**views, "left": {"a": np.full((5, 3), np.nan)}}, MESHES)
    with pytest.raises(TouchCalibrationError, match=r"views\['left'\].*'c'"):
        solve_cell(touches, predicted, {**views, "left": {"c": np.zeros((5, 3))}}, MESHES)
    with pytest.raises(TouchCalibrationError, match="models.*'b'"):
        solve_cell(touches, predicted, views, {"a": MESHES["a"]})


def test_a_fit_of_one_iteration_is_finite() -> None:
    touches, predicted, views = _small_cell()
    cell = solve_cell(touches, predicted, views, MESHES, iterations=1)
    assert all(np.isfinite(pose).all() for pose in (*cell.cameras.values(), *cell.objects.values()))


# -- a touch's own fit -------------------------------------------------------------------------


def _ssd() -> np.ndarray:
    x, z, y = np.meshgrid(*GRID, indexing="ij")
    return 50.0 + 3.0 * (x - 0.1) ** 2 + 2.0 * (z + 0.05) ** 2 + y**2


@pytest.mark.parametrize("bad", [np.nan, np.inf, -np.inf, -1.0])
def test_a_non_finite_or_negative_ssd_is_refused(bad: float) -> None:
    ssd = _ssd()
    ssd[1, 2, 0] = bad
    with pytest.raises(TouchCalibrationError, match="ssd"):
        profiled_fit(ssd, GRID, pixels=100)


@pytest.mark.parametrize("pixels", [0, -3, 2.5, True])
def test_a_fit_over_no_pixels_is_refused(pixels: int) -> None:
    with pytest.raises(TouchCalibrationError, match="pixels"):
        profiled_fit(_ssd(), GRID, pixels=pixels)


@pytest.mark.parametrize(
    "grid",
    [
        (np.array([0.0, np.nan, 0.8]), GRID[1], GRID[2]),
        (np.array([0.4, 0.0, -0.4]), GRID[1], GRID[2]),
        (np.array([-0.4, 0.0, 0.5]), GRID[1], GRID[2]),
        (GRID[0], GRID[1]),
    ],
)
def test_a_grid_not_evenly_rising_is_refused(grid: tuple[np.ndarray, ...]) -> None:
    with pytest.raises(TouchCalibrationError, match="grid_mm"):
        profiled_fit(_ssd(), grid, pixels=100)  # type: ignore[arg-type]


@settings(max_examples=30, deadline=None, derandomize=True)
@given(st.floats(0.0, 1e12), st.integers(1, 10**7))
def test_a_finite_ssd_gives_a_finite_touch(floor: float, pixels: int) -> None:
    """A zero-residual minimum (a perfect match) included: the information stays finite."""
    fit, information = profiled_fit(_ssd() - 50.0 + floor, GRID, pixels=pixels)
    assert np.isfinite(fit).all() and np.isfinite(information).all()
    _touch(offset_gel_mm=fit[:2], information_gel=information)  # the touch it makes is accepted


# -- table levelling ---------------------------------------------------------------------------


def _line(rng: np.random.Generator, noise_m: float) -> np.ndarray:
    t = rng.uniform(-0.3, 0.3, 500)
    return np.column_stack([t, 0.5 * t, 0.01 * t]) + rng.normal(0, noise_m, (500, 3))


@pytest.mark.parametrize(
    "points",
    [
        np.tile([0.1, 0.2, 0.0], (500, 1)),
        _line(np.random.default_rng(4), 0.0),
        _line(np.random.default_rng(5), 0.0005),
    ],
    ids=["identical", "collinear", "collinear-noisy"],
)
def test_a_table_of_identical_or_collinear_points_is_refused(points: np.ndarray) -> None:
    with pytest.raises(TouchCalibrationError, match="points_world_m"):
        table_levelling(points)


def test_a_table_cloud_malformed_is_refused_by_name() -> None:
    rng = np.random.default_rng(6)
    table = np.column_stack([rng.uniform(-0.3, 0.3, (500, 2)), rng.normal(0, 0.001, 500)])
    for bad in (np.where(np.arange(500)[:, None] == 3, np.nan, table), table[:, :2], table[:50]):
        with pytest.raises(TouchCalibrationError, match="points_world_m"):
            table_levelling(bad)
    for inlier in (0.0, -0.004, np.nan, np.inf):
        with pytest.raises(TouchCalibrationError, match="inlier_m"):
            table_levelling(table, inlier_m=inlier)
    levelled = table_levelling(table)
    assert pose_error(levelled, np.eye(4))[1] < 0.5  # the good table still levels


# -- a depth-map moved -------------------------------------------------------------------------


def test_a_depth_map_moved_by_a_bad_shift_or_pitch_is_refused() -> None:
    depth = np.full((10, 12), 0.003, np.float32)
    depth[3:6, 4:8] = 0.0005
    for shift in ([np.nan, 0.0, 0.0], [0.0, np.inf, 0.0], [0.0, 0.0, np.nan], [0.0, 0.0]):
        with pytest.raises(TouchCalibrationError, match="shift_gel_mm"):
            moved_depth_map(depth, (0.2, 0.2), np.array(shift), 0.003)
    for pitch in ((0.0, 0.2), (0.2, -0.1), (np.nan, 0.2), (0.2, np.inf)):
        with pytest.raises(TouchCalibrationError, match="bin_pitch_mm"):
            moved_depth_map(depth, pitch, np.zeros(3), 0.003)
    for bad_map in (np.where(depth < 0.001, np.nan, depth), depth[0], np.zeros((0, 4))):
        with pytest.raises(TouchCalibrationError, match="depth_map_m"):
            moved_depth_map(bad_map, (0.2, 0.2), np.zeros(3), 0.003)
    with pytest.raises(TouchCalibrationError, match="y_far_m"):
        moved_depth_map(depth, (0.2, 0.2), np.zeros(3), np.nan)
    moved = moved_depth_map(depth, (0.2, 0.2), np.array([0.2, 0.0, 0.1]), 0.003)
    assert (moved < 0.003).sum() == (depth < 0.003).sum()  # the contact is kept, moved one bin
