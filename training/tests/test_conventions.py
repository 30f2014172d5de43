"""The Python geometry must agree with the Rust crate on the shared fixture."""

import json
from pathlib import Path

import numpy as np
import pytest

from cmr import geometry as g

FIXTURE = json.loads((Path(__file__).resolve().parents[2] / "fixtures" / "conventions.json").read_text())
TOL = 1e-9


def test_action_sets():
    assert np.allclose(FIXTURE["action_set"]["rotation_deg"], g.ROTATION_STEPS_DEG, atol=TOL)
    assert np.allclose(FIXTURE["action_set"]["translation_m"], g.TRANSLATION_STEPS_M, atol=TOL)


@pytest.mark.parametrize("case", FIXTURE["projection"])
def test_projection(case):
    k = np.array([FIXTURE["intrinsics"][n] for n in ("fx", "fy", "cx", "cy")])
    p = np.array([case["point_cam"]])
    uv, valid = g.project(k, p)
    assert bool(valid[0]) == (case["uv"] is not None)
    if case["uv"] is not None:
        assert np.allclose(uv[0], case["uv"], atol=1e-9)
    assert bool(g.in_frustum(k, p, 512, 160)[0]) == case["in_frustum"]


@pytest.mark.parametrize("case", FIXTURE["preprocess"])
def test_preprocess(case):
    w, h = case["in_size"]
    scale = g.input_scale(case["nominal_scale"], case["focal_range_px"], case["intrinsics"]["fx"])
    assert scale == case["scale"]
    plan = g.preprocess_plan(w, h, scale, 512, 160)
    assert plan == case["plan"]
    k = [case["intrinsics"][n] for n in ("fx", "fy", "cx", "cy")]
    adjusted = g.adjust_intrinsics(plan, k, w, h)
    assert np.allclose(adjusted, [case["adjusted"][n] for n in ("fx", "fy", "cx", "cy")], atol=1e-9)


@pytest.mark.parametrize("case", FIXTURE["preprocess_zoomed"])
def test_preprocess_zoomed(case):
    """The judge's views (`PreprocessPlan::zoomed`): training's zoomed plan with the crop at the
    left edge, centre or right edge, centred down the height."""
    w, h = case["in_size"]
    rw, rh = g.resized_size(w, h, case["scale"], 512, 160, case["zoom"])
    x0 = {"left": 0, "centre": (rw - 512) // 2, "right": rw - 512}[case["anchor"]]
    plan = g.preprocess_plan(w, h, case["scale"], 512, 160, (x0, (rh - 160) // 2), case["zoom"])
    assert plan == case["plan"]
    k = [case["intrinsics"][n] for n in ("fx", "fy", "cx", "cy")]
    adjusted = g.adjust_intrinsics(plan, k, w, h)
    assert np.allclose(adjusted, [case["adjusted"][n] for n in ("fx", "fy", "cx", "cy")], atol=1e-9)


@pytest.mark.parametrize("case", FIXTURE["poses"])
def test_pose_conventions(case):
    current, target = np.array(case["current"]), np.array(case["target"])
    pivot = np.array(case["pivot_map"])
    yaw, tx, tz = g.step_values(case["action_indices"])
    assert np.allclose(g.apply_action(current, pivot, yaw, tx, tz), case["after_action"], atol=1e-9)
    assert np.allclose(g.needed_motion(current, target, pivot), case["needed_motion"], atol=1e-9)
    assert list(g.expert_indices(current, target, pivot)) == case["expert_indices"]
    points = np.array(case["points_map"])
    before = g.p2p_distance(current, target, points)
    after = g.p2p_distance(np.array(case["after_action"]), target, points)
    assert abs(before - case["p2p_before"]) < 1e-9 and abs(after - case["p2p_after"]) < 1e-9
    assert g.step_reward(before, after) == case["reward"]
    err = g.pose_error(current, target)
    for key in ("rte_m", "rre_euler_deg", "rre_geodesic_deg"):
        assert abs(err[key] - case[key]) < 1e-7


def test_start_yaw_offsets():
    """The multi-start search's starts; a missing key fails (the Rust tests write it)."""
    table = FIXTURE["start_yaw_offsets_deg"]
    assert table
    for h, offsets in table.items():
        ours = g.start_yaw_offsets(int(h))
        assert len(ours) == len(offsets) and np.allclose(ours, offsets, atol=TOL), (h, ours, offsets)


# ---------------------------------------------------------------------------------------------
# The map_z action frame (yaw about the map's up axis), on pitched and rolled rigs.

@pytest.mark.parametrize("case", FIXTURE["map_z_poses"])
def test_map_z_conventions(case):
    current, target = np.array(case["current"]), np.array(case["target"])
    pivot = np.array(case["pivot_map"])
    right, forward = g.ground_heading(current)
    assert np.allclose(right, case["ground_right"], atol=TOL) and np.allclose(forward, case["ground_forward"], atol=TOL)
    yaw, tx, tz = g.step_values(case["action_indices"])
    moved = g.apply_action(current, pivot, yaw, tx, tz, frame=g.MAP_Z)
    assert np.allclose(moved, case["after_action"], atol=1e-9)
    # The map's up axis as the camera sees it (its pitch and roll) does not change.
    assert np.allclose(moved[:3, :3] @ [0, 0, 1], current[:3, :3] @ [0, 0, 1], atol=1e-12)
    assert np.allclose(g.needed_motion(current, target, pivot, g.MAP_Z), case["needed_motion"], atol=1e-9)
    assert list(g.expert_indices(current, target, pivot, g.MAP_Z)) == case["expert_indices"]


@pytest.mark.parametrize("case", FIXTURE["map_z_expert_rollouts"])
def test_map_z_expert_rollout(case):
    truth, pivot = np.array(case["truth"]), np.array(case["pivot_map"])
    pose = np.array(case["start"])
    for expected in case["expert_steps"]:
        indices = g.expert_indices(pose, truth, pivot, g.MAP_Z)
        assert list(indices) == expected
        pose = g.apply_action(pose, pivot, *g.step_values(indices), frame=g.MAP_Z)
    assert np.allclose(pose, case["final"], atol=1e-9)
    err = g.pose_error(pose, truth)
    assert err["rre_geodesic_deg"] < 0.06 and err["rte_m"] < 0.1


@pytest.mark.parametrize("case", FIXTURE["poses"])
def test_map_z_equals_camera_y_for_a_near_level_camera(case):
    """For a level camera (the fixture's pose with its tilt removed) map_z is camera_y."""
    current, pivot = np.array(case["current"]), np.array(case["pivot_map"])
    yaw, tx, tz = g.step_values(case["action_indices"])
    level = current.copy()
    level[:3, :3] = np.array([[0, -1, 0], [0, 0, -1], [1, 0, 0.0]]) @ g.rot_z(yaw * 0.37 + 11.0)
    a = g.apply_action(level, pivot, yaw, tx, tz, frame=g.CAMERA_Y)
    b = g.apply_action(level, pivot, yaw, tx, tz, frame=g.MAP_Z)
    assert np.allclose(a, b, atol=1e-12)
    assert np.allclose(g.needed_motion(level, current, pivot, g.CAMERA_Y), g.needed_motion(level, current, pivot, g.MAP_Z),
                       atol=1e-9) or abs(current[1, 2]) > 0  # current is tilted: only the level pose is exact


def test_unknown_frame_is_refused():
    with pytest.raises(ValueError):
        g.apply_action(np.eye(4), np.zeros(3), 1.0, 0.0, 0.0, frame="camera_z")


def test_checkpoints_name_their_action_frame():
    """export and evaluate read the frame from a checkpoint's config; older ones are camera_y."""
    from cmr.export import action_frame_of, manifest
    assert action_frame_of({}) == g.CAMERA_Y
    assert action_frame_of({"config": {"action_frame": "map_z"}}) == g.MAP_Z
    with pytest.raises(ValueError):
        action_frame_of({"config": {"action_frame": "map_y"}})
    assert manifest({}, {}, {}, {}, g.MAP_Z)["actions"]["frame"] == "map_z"
    assert manifest({}, {}, {}, {})["actions"]["frame"] == "camera_y"


def test_virtual_scan_matches_the_server():
    """The tiled region's crop (`maps::tiles::virtual_scan`): the same points kept, in the same
    order; the fixture's pairs on one ray keep only their nearer point."""
    from cmr.data import SCAN_BEAMS, SCAN_COLUMNS, SCAN_ELEVATION_DEG, virtual_scan

    case = FIXTURE["virtual_scan"]
    assert (SCAN_BEAMS, SCAN_COLUMNS, list(SCAN_ELEVATION_DEG)) == (case["beams"], case["columns"], case["elevation_deg"])
    points = np.array(case["points"], dtype=np.float64)
    kept = virtual_scan(points, case["sensor"], case["radius_m"])
    assert kept.tolist() == case["indices"]
    pairs = np.arange(600, len(points)).reshape(-1, 2)  # (farther, nearer) on one ray
    assert not np.isin(pairs[:, 0], kept).any() and 0.5 * len(pairs) < np.isin(pairs[:, 1], kept).sum()


# ---------------------------------------------------------------------------------------------
# The intensity rank an intensity point encoder reads (Rust: maps::intensity_rank).

@pytest.mark.parametrize("case", FIXTURE["intensity_rank"], ids=lambda c: c["name"])
def test_intensity_rank_matches_the_server(case):
    """The same float32 ranks to the bit: ties share their mid-rank, 0 and -0 tie, a constant
    reads 0.5 everywhere, an empty cloud gives nothing."""
    from cmr.data import intensity_rank

    ours = intensity_rank(np.array(case["values"], dtype=np.float32))
    assert ours.dtype == np.float32 and ours.shape == (len(case["values"]),)
    assert ours.tolist() == np.array(case["ranks"], dtype=np.float32).tolist()
    if case["name"] == "constant":
        assert set(ours.tolist()) == {0.5}


def test_the_intensity_rank_fixture_has_ties():
    names = {c["name"]: c for c in FIXTURE["intensity_rank"]}
    assert set(names) >= {"mixed", "constant", "empty"}
    mixed = names["mixed"]["values"]
    assert len(mixed) >= 30 and len(set(mixed)) < len(mixed) - 10


# ---------------------------------------------------------------------------------------------
# The rotation check every reader of poses and calibration applies (Rust: geometry::check_rotation).

def test_rotation_tolerance_is_the_same():
    assert FIXTURE["rotation_check"]["tolerance"] == g.ROTATION_TOLERANCE


@pytest.mark.parametrize("case", FIXTURE["rotation_check"]["cases"], ids=lambda c: c["name"])
def test_rotation_check(case):
    """Same verdict and the same message as Rust, for every fixture case."""
    matrix = np.array([[float(v) for v in row] for row in case["matrix"]])
    if case["error"] is None:
        g.check_rotation(matrix)
    else:
        with pytest.raises(ValueError) as e:
            g.check_rotation(matrix)
        assert str(e.value) == case["error"]
