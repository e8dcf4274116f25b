"""Hard cases of issue 52, requests and passes and the small helpers: each gives the right
answer or its module's own error naming the argument, in bounded time.

The inference request's scalars (pose_sigma_mm, dropout_samples) and the forward passes'
max_batch; ADD and ADD-S; strict JSON of cycles, numpy keys and long doubles; Progress totals;
touches_of_grasps' count; the physics prior's reading of a NaN bin. Hypothesis runs
derandomized, so every run draws the same examples."""

from __future__ import annotations

import io
import json
import math
import sys
from types import SimpleNamespace
from typing import Any

import numpy as np
import open3d as o3d
import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from dataset.records import DatasetError, SampleRecord
from dataset.touches import touches_of_grasps
from models.prior import PhysicsPrior, PriorSpec
from models.prior_tensor import TensorPrior
from msgs import strict_json
from msgs.inference import TactileEstimateRequest
from msgs.progress import MAX_TOTAL, Progress
from nodes.inference_passes import forward_pass_parts, max_batch_on
from nodes.inference_requests import BadRequest, checked_regions
from perception.errors import PerceptionError
from perception.pose_scores import add_error_m, add_s_error_m
from sim.gelsight import GAP_LIMIT_MM

pytestmark = pytest.mark.filterwarnings("error")  # a RuntimeWarning on the way fails the case

CASES = settings(max_examples=40, deadline=None, derandomize=True)
PARAMS = SimpleNamespace(max_regions=8, max_points=1000)
SCENE = "scenes/ycb_three.yaml"
CROP_M = (0.024, 0.015, 0.019)
BINS = 24

# What an in-process client may put in a scalar field: anything.
HOSTILE = [True, False, np.bool_(True), "0.3", "", "x" * 100_000, None, 10**400, -(10**400), [1], {"a": 1}, b"1"]


# --- requests and passes ---------------------------------------------------------------------


def request(**fields: Any) -> TactileEstimateRequest:
    return TactileEstimateRequest(depth_maps=np.zeros((2, 100, 100), np.float32), **fields)


@pytest.mark.parametrize(
    "sigma", [*HOSTILE, math.nan, math.inf, -math.inf, 5.000001, 1e300, np.longdouble(1), complex(1, 0)]
)
def test_a_pose_sigma_that_is_no_finite_number_of_mm_is_a_bad_request(sigma: Any) -> None:
    with pytest.raises(BadRequest, match="pose_sigma_mm") as caught:
        checked_regions(request(pose_sigma_mm=sigma), PARAMS, 100)
    assert len(str(caught.value)) < 400  # a hostile value is named, not copied whole


@pytest.mark.parametrize("sigma", [0, 0.0, 0.3, 5, 5.0, -1.0, -1e300, np.float32(0.3), np.float64(2.0), np.int64(1)])
def test_a_pose_sigma_of_mm_or_a_negative_default_is_served(sigma: Any) -> None:
    assert checked_regions(request(pose_sigma_mm=sigma), PARAMS, 100) == 2


@pytest.mark.parametrize("samples", [*HOSTILE, 1.0, 0, 2, -1, np.float64(1.0)])
def test_dropout_samples_other_than_the_integer_1_is_a_bad_request(samples: Any) -> None:
    with pytest.raises(BadRequest, match="dropout_samples") as caught:
        checked_regions(request(dropout_samples=samples), PARAMS, 100)
    assert len(str(caught.value)) < 400


@pytest.mark.parametrize("samples", [1, np.int64(1), np.uint8(1)])
def test_dropout_samples_of_1_is_served(samples: Any) -> None:
    assert checked_regions(request(dropout_samples=samples), PARAMS, 100) == 2


@CASES
@given(
    value=st.one_of(st.none(), st.booleans(), st.integers(), st.floats(), st.text(max_size=20), st.binary(max_size=4)),
    field=st.sampled_from(["pose_sigma_mm", "dropout_samples"]),
)
def test_any_scalar_is_served_or_a_bad_request(value: Any, field: str) -> None:
    """Never TypeError or OverflowError from inside the check: the node's bad_request reply."""
    try:
        assert checked_regions(request(**{field: value}), PARAMS, 100) == 2
    except BadRequest as exc:
        assert field in str(exc)


@pytest.mark.parametrize("max_batch", [0, -1, -(10**400), True, 2.5, None, "8"])
def test_passes_of_no_room_are_refused_not_looped_over(max_batch: Any) -> None:
    with pytest.raises(ValueError, match="max_batch"):
        forward_pass_parts([3, 2], max_batch)


@pytest.mark.parametrize("lanes", [0, -1, True, 1.5, None])
def test_passes_spread_over_no_lanes_are_refused(lanes: Any) -> None:
    with pytest.raises(ValueError, match="lanes"):
        forward_pass_parts([3, 2], 4, lanes)


def test_a_negative_region_count_is_refused() -> None:
    with pytest.raises(ValueError, match="regions"):
        forward_pass_parts([3, -2], 4)
    assert forward_pass_parts([], 4) == [[]]  # no requests: one empty pass, as before


@pytest.mark.parametrize(("device", "asked"), [("cpu", -1), ("tpu", 0), ("cpu", True)])
def test_a_device_width_is_asked_for_a_known_device_and_a_width_of_zero_or_more(device: str, asked: Any) -> None:
    with pytest.raises(ValueError, match="max_batch|device"):
        max_batch_on(device, asked)


# --- ADD and ADD-S ---------------------------------------------------------------------------


def box() -> o3d.geometry.TriangleMesh:
    mesh = o3d.geometry.TriangleMesh.create_box(0.04, 0.02, 0.01)
    mesh.translate((-0.02, -0.01, -0.005))
    return mesh


def shifted(dx: float) -> np.ndarray:
    pose = np.eye(4)
    pose[0, 3] = dx
    return pose


def test_add_and_add_s_of_no_points_are_refused_naming_them() -> None:
    none = np.zeros((0, 3))
    with pytest.raises(PerceptionError, match="model_points_m"):
        add_error_m(none, np.eye(4), np.eye(4))
    with pytest.raises(PerceptionError, match="model_points_m"):
        add_s_error_m(box(), none, np.eye(4), np.eye(4))


def test_add_s_against_a_mesh_of_no_triangles_is_refused_naming_it() -> None:
    points = np.asarray(box().vertices)
    with pytest.raises(PerceptionError, match="surface"):
        add_s_error_m(o3d.geometry.TriangleMesh(), points, np.eye(4), np.eye(4))
    with pytest.raises(PerceptionError, match="surface"):
        add_s_error_m("box.ply", points, np.eye(4), np.eye(4))  # type: ignore[arg-type]


@pytest.mark.parametrize(
    ("points", "estimate", "match"),
    [
        (np.full((4, 3), np.nan), np.eye(4), "model_points_m"),
        (np.zeros((4, 2)), np.eye(4), "model_points_m"),
        (np.array([["a", "b", "c"]]), np.eye(4), "model_points_m"),
        (np.zeros((4, 3)), np.full((4, 4), np.inf), "estimate_to_world"),
        (np.zeros((4, 3)), np.eye(3), "estimate_to_world"),
    ],
)
def test_points_and_poses_that_are_not_real_are_refused_naming_them(
    points: np.ndarray, estimate: np.ndarray, match: str
) -> None:
    with pytest.raises(PerceptionError, match=match):
        add_error_m(points, estimate, np.eye(4))
    with pytest.raises(PerceptionError, match=match):
        add_s_error_m(box(), points, estimate, np.eye(4))


@CASES
@given(dx=st.floats(-0.05, 0.05), count=st.integers(1, 50))
def test_add_of_a_shift_is_its_length_and_add_s_at_most_that(dx: float, count: int) -> None:
    points = np.random.default_rng(count).uniform(-0.01, 0.01, (count, 3))
    assert add_error_m(points, shifted(dx), np.eye(4)) == pytest.approx(abs(dx), abs=1e-12)
    on_surface = np.asarray(box().sample_points_uniformly(count).points)
    assert add_s_error_m(box(), on_surface, shifted(dx), np.eye(4)) <= abs(dx) + 1e-6


def test_a_single_point_scores_its_own_distance() -> None:
    corner = np.array([[0.02, 0.01, 0.005]])  # on the box's surface
    assert add_error_m(corner, np.eye(4), np.eye(4)) == 0.0
    assert add_s_error_m(box(), corner, np.eye(4), np.eye(4)) == pytest.approx(0.0, abs=1e-7)


# --- strict JSON -----------------------------------------------------------------------------


def test_a_cycle_is_refused_naming_where_it_closes() -> None:
    loop: list[Any] = [1]
    loop.append({"back": loop})
    with pytest.raises(ValueError, match=r"\$\[1\]\.back.*cycle"):
        strict_json.dumps(loop)
    shared = [1.5]  # the same list twice is no cycle
    assert json.loads(strict_json.dumps({"a": shared, "b": shared})) == {"a": [1.5], "b": [1.5]}


def test_nesting_deeper_than_any_report_is_refused_not_a_recursion_error() -> None:
    deep: list[Any] = []
    for _ in range(sys.getrecursionlimit() * 2):
        deep = [deep]
    with pytest.raises(ValueError, match="deep"):
        strict_json.dumps(deep)


@pytest.mark.parametrize(
    ("key", "text"),
    [(np.int64(3), "3"), (np.uint8(7), "7"), (np.float32(0.5), "0.5"), (np.bool_(True), "true"), (2, "2")],
)
def test_numpy_scalar_keys_are_written_as_json_writes_their_python_value(key: Any, text: str) -> None:
    assert json.loads(strict_json.dumps({key: 1})) == {text: 1}


@pytest.mark.parametrize("key", [math.nan, np.float64(math.inf), (1, 2), b"k"])
def test_a_key_json_cannot_hold_is_refused_naming_it(key: Any) -> None:
    with pytest.raises(ValueError, match=r"\$ has a key"):
        strict_json.dumps({key: 1})


def test_long_doubles_are_numbers_and_a_non_finite_one_needs_its_reason() -> None:
    assert json.loads(strict_json.dumps({"x": np.longdouble(0.25)})) == {"x": 0.25}
    assert json.loads(strict_json.dumps(np.array([0.5, 1.5], np.longdouble))) == [0.5, 1.5]
    with pytest.raises(ValueError, match=r"\$\.x is inf"):
        strict_json.dumps({"x": np.longdouble("inf")})
    assert json.loads(strict_json.dumps({"x": np.longdouble("nan"), "x_undefined": "why"}))["x"] is None
    if np.finfo(np.longdouble).max > np.finfo(np.float64).max:  # x86's 80-bit long double
        with pytest.raises(ValueError, match=r"\$\.x .*float64"):
            strict_json.dumps({"x": np.longdouble("1e4000")})


def test_a_value_json_has_no_form_for_is_refused_naming_it() -> None:
    with pytest.raises(ValueError, match=r"\$\.s"):
        strict_json.dumps({"s": {1, 2}})
    with pytest.raises(ValueError, match=r"\$\.c"):
        strict_json.dumps({"c": np.complex128(1 + 2j)})


# --- Progress --------------------------------------------------------------------------------


@pytest.mark.parametrize(
    ("total", "initial"),
    [(None, 0), (MAX_TOTAL + 1, 0), (10**400, 0), (1e400, 0), (2.5, 0), (True, 0), ("10", 0), (10, None), (10, 1.5)],
)
def test_a_total_that_is_no_count_a_float_holds_is_refused_naming_it(total: Any, initial: Any) -> None:
    with pytest.raises(ValueError, match="total|initial"):
        Progress("work", total, "steps", initial=initial, stream=io.StringIO())  # type: ignore[arg-type]


@pytest.mark.parametrize("total", [0, 1, MAX_TOTAL, np.int64(12)])
def test_the_largest_total_runs_to_its_end(total: int, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv("DTX_TERMINAL", "0")
    clock = iter(float(t) for t in range(100))
    lines = io.StringIO()
    with Progress("work", total, "steps", stream=lines, clock=lambda: next(clock)) as progress:
        progress.update(min(int(total), 3))
        assert "work: " in progress.line()
    assert lines.getvalue().count("\n") >= 1 and "steps" in lines.getvalue()


# --- touches of grasps -----------------------------------------------------------------------


def sample(grasp: int, finger: str) -> SampleRecord:
    return SampleRecord(
        f"g{grasp}_{finger}",
        "box",
        grasp,
        finger,
        (0, 0, 0, 0),
        {},
        1.0,
        {},
        {},
        gel_to_world=tuple(map(tuple, np.eye(4))),
    )


@pytest.mark.parametrize("grasps", [-1, -(10**400), True, 1.5, None, "2"])
def test_a_count_of_grasps_that_is_no_count_is_refused_naming_it(grasps: Any) -> None:
    records = [sample(g, f) for g in range(3) for f in ("left", "right")]
    with pytest.raises(DatasetError, match="grasps"):
        touches_of_grasps(records, "box", grasps)
    with pytest.raises(DatasetError, match="grasps"):
        touches_of_grasps([], "box", grasps)


@pytest.mark.parametrize("grasps", [0, 1, 2, 3, 10**400, np.int64(2)])
def test_both_fingers_of_at_most_the_count_of_grasps(grasps: int) -> None:
    records = [sample(g, f) for g in range(3) for f in ("left", "right")]
    chosen = touches_of_grasps(records, "box", grasps)
    assert len(chosen) == 2 * min(int(grasps), 3)
    assert len({r.grasp_id for r in chosen}) == min(int(grasps), 3)


# --- the physics prior's NaN bin -------------------------------------------------------------


@pytest.fixture(scope="module")
def prior() -> PhysicsPrior:
    return PhysicsPrior(PriorSpec(SCENE, CROP_M, pose_sigma_mm=1.0), BINS)


def pressed_square() -> np.ndarray:
    maps = np.full((1, BINS, BINS), 0.004, np.float32)  # y_far: nothing near
    maps[0, 8:16, 8:16] = -0.0008
    return maps


@pytest.mark.parametrize("sigma_mm", [0.0, 1.0])
@pytest.mark.parametrize("where", [(10, 11), (8, 8), (2, 20)])  # inside the press, its corner, far off
def test_a_nan_bin_is_nothing_there_as_an_infinite_one_is_in_both_forms(
    prior: PhysicsPrior, sigma_mm: float, where: tuple[int, int]
) -> None:
    """models.data.depth_input's contract (NaN/+inf = empty bin), kept by the prior: a NaN bin
    draws exactly what an empty bin of +inf, or of a gap at the renderer's limit, draws; on the
    CPU and in the tensor form a GPU serves; as images and as the network's channels."""
    empties = {}
    for name, value in (("nan", np.nan), ("inf", np.inf), ("limit", GAP_LIMIT_MM * 1e-3)):
        maps = pressed_square()
        maps[0][where] = value
        empties[name] = maps
    drawn = {name: prior.images(maps, sigma_mm) for name, maps in empties.items()}
    np.testing.assert_array_equal(drawn["nan"], drawn["inf"])
    np.testing.assert_array_equal(drawn["nan"], drawn["limit"])
    assert torch.equal(prior.channels(empties["nan"], sigma_mm), prior.channels(empties["inf"], sigma_mm))
    tensor = TensorPrior(prior.renderer, (CROP_M[0], CROP_M[2]))
    on_device = {name: tensor.images(torch.from_numpy(maps), sigma_mm) for name, maps in empties.items()}
    assert torch.equal(on_device["nan"], on_device["inf"]) and torch.equal(on_device["nan"], on_device["limit"])


def test_a_nan_bin_where_nothing_was_changes_no_pixel_and_a_map_of_nan_is_the_background(
    prior: PhysicsPrior,
) -> None:
    """Nothing there where nothing was near: the image is the press's alone; and a map of
    nothing but NaN bins is the gel untouched."""
    maps = pressed_square()
    holed = maps.copy()
    holed[0, 2, 20] = np.nan
    for sigma_mm in (0.0, 1.0):
        np.testing.assert_array_equal(prior.images(holed, sigma_mm), prior.images(maps, sigma_mm))
        nothing = prior.images(np.full((1, 7, 9), np.nan), sigma_mm)[0]
        np.testing.assert_array_equal(nothing, prior.renderer.background())
