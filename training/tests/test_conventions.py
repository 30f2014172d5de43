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
    plan = g.preprocess_plan(w, h, 0.5, 512, 160)
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
