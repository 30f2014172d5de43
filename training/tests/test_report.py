"""Evaluation figures and the model card come from real runs of the pipeline."""

import json

import numpy as np

from cmr.data import find_sequences, list_frames
from cmr.evaluate import evaluate
from cmr.export import export_models
from cmr.model_card import data_summary, render
from cmr.models import build_all


def test_evaluation_and_model_card(tmp_path, tiny_dataset):
    models = build_all()
    frames = list_frames(find_sequences(tiny_dataset))[:2]
    result = evaluate(models, frames, iterations=3, num_points=2048, chunk=2)
    assert [r["iteration"] for r in result["agent"]] == [1, 2, 3]
    assert result["expert"][-1]["rte_m"] < result["initial"]["rte_m"]  # the teacher makes progress
    assert 0.0 <= result["frustum"]["precision"] <= 1.0 and 0.0 <= result["match_accuracy"] <= 1.0
    doc = export_models(models, tmp_path, dict(data="test", seeds={}), dict(final=result["agent"][-1]))
    text = render(doc, result, {"agent_ms": 1.0}, data_summary([str(tiny_dataset)]), [], "curves.png", "note")
    assert "| 3 |" in text and "Greedy expert" in text and str(sum(doc["parameters"].values())) not in ("0",)
    assert json.loads((tmp_path / "manifest.json").read_text())["validation"]["final"]["iteration"] == 3
    assert result["hypotheses"] == 1 and "agent_single_start" not in result and "single start" not in text

    multi = evaluate(models, frames, iterations=3, num_points=2048, chunk=2, hypotheses=2)
    assert multi["hypotheses"] == 2 and [r["iteration"] for r in multi["agent"]] == [1, 2, 3]
    for one, single in zip(result["agent"], multi["agent_single_start"]):  # hypothesis 0 = the single start
        assert all(abs(one[k] - single[k]) < 1e-6 for k in one)
    text = render(doc, multi, {"agent_ms": 1.0}, [], [], "curves.png", "note")
    assert "multi-start search with 2 starts" in text and "single start (the paper's protocol" in text


def test_alignment_diagnosis_rewards_a_perfect_embedding(tiny_dataset):
    """With point features equal to the (random) image feature at each point's true projection, the
    true pose scores ~1 and beats every perturbation, where points land on unrelated cells."""
    import numpy as np
    import torch

    from cmr.diagnose import PERTURBATIONS, alignment_score
    from cmr.data import make_sample
    from cmr.episodes import embed
    from cmr.state import frustum_cells, to_camera

    models = build_all()
    frames = list_frames(find_sequences(tiny_dataset))[:2]
    samples = [make_sample(f, np.random.default_rng(i), train=False, num_points=4096) for i, f in enumerate(frames)]
    eps = embed(models, samples, torch.device("cpu"))
    gen = torch.Generator().manual_seed(0)
    for row, s in enumerate(samples):
        grid = torch.nn.functional.normalize(torch.randn(64, 40 * 128, generator=gen), dim=0)
        eps.image_features[row] = grid.view(64, 40, 128)
        cell, inside = frustum_cells(eps.intrinsics[row:row + 1],
                                     to_camera(torch.as_tensor(s.truth[None], dtype=torch.float32), eps.points[row:row + 1]))
        feats = torch.nn.functional.normalize(torch.randn(len(s.points), 64, generator=gen), dim=1)
        feats[inside[0]] = grid[:, cell[0][inside[0]]].t()
        eps.point_features[row] = feats
    from cmr import geometry as g
    for row, s in enumerate(samples):
        truth = alignment_score(eps, row, s.truth)
        assert truth > 0.99
        for _, yaw, tx, tz in PERTURBATIONS:
            assert alignment_score(eps, row, g.apply_action(s.truth, eps.pivots[row], yaw, tx, tz)) < truth


def test_frozen_cases_reproduce_the_harness_motions(tmp_path, tiny_dataset):
    """`--perturbations` evaluates the Rust harness's own cases: same frames, same motions Q."""
    from cmr import geometry as g
    from cmr.data import make_sample
    from cmr.evaluate import frozen_cases
    frames = list_frames(find_sequences(tiny_dataset))
    seq, idx = frames[1].sequence.name, frames[1].index
    path = tmp_path / "cases.json"
    path.write_text(json.dumps({"format": "cmr-agent-perturbations/1", "seed": 0, "sampling_seed": 0, "cases": [
        {"sequence": seq, "frame": idx, "yaw_deg": 30.0, "dx_m": 3.0, "dy_m": -4.0}]}))
    picked, motions = frozen_cases(frames, path)
    assert picked == [frames[1]]
    s = make_sample(picked[0], np.random.default_rng(0), train=False, num_points=512, motion=motions[0])
    err = g.pose_error(s.initial, s.truth)
    assert abs(err["rre_geodesic_deg"] - 30.0) < 1e-6
    assert np.allclose(s.motion, g.ground_motion(np.radians(30.0), 3.0, -4.0))


def level_camera():
    """A level camera (map z up) off the origin: the pose both grids of `cmr.diagnose` are tested about."""
    pose = np.eye(4)
    pose[:3, :3] = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, -1.0], [0.0, 1.0, 0.0]])
    pose[:3, 3] = [0.3, 1.6, -2.0]
    return pose


def turn_deg(a, b):
    """How far pose b's ground heading is turned from pose a's, counter-clockwise about map z, in (-180, 180]."""
    from cmr import geometry as g
    fa, fb = g.ground_heading(a)[1], g.ground_heading(b)[1]
    return float(np.degrees(np.arctan2(np.cross(fa, fb)[2], fa @ fb)))


def test_global_poses_sweep_the_heading_and_draw_protocol_starts():
    """`cmr.diagnose.global_poses`: 72 headings 5 deg apart at the true camera centre, then starts
    within +-10 m in the ground plane at any heading, with the registered ones flagged."""
    import math

    from cmr import geometry as g
    from cmr.diagnose import global_poses
    pose = level_camera()
    poses, far = global_poses(pose, np.random.default_rng(0), 300)
    assert len(poses) == 372 and far.shape == (300,)
    centre = g.invert(pose)[:3, 3]
    for i, p in enumerate(poses[:72]):
        assert np.allclose(g.invert(p)[:3, 3], centre)
        assert abs((turn_deg(pose, p) - 5.0 * i + 180.0) % 360.0 - 180.0) < 1e-6
    moved = np.array([g.invert(p)[:3, 3] - centre for p in poses[72:]])
    assert np.allclose(moved[:, 2], 0.0) and np.abs(moved[:, :2]).max() <= 10.0 * math.sqrt(2) + 1e-9
    errs = [g.pose_error(p, pose) for p in poses[72:]]
    assert np.array_equal(far, [e["rte_m"] >= 5.0 or e["rre_euler_deg"] >= 10.0 for e in errs])
    assert 0 < (~far).sum() < 30  # a few starts land within 5 m / 10 deg


def test_peak_grid_turns_about_the_camera_and_shifts_on_the_ground():
    """`cmr.diagnose.peak_grid`: 5 turns x 81 lattice shifts within 5 m; the turns keep the camera
    centre, the shifts move it by exactly their length in the ground plane, at the turned heading."""
    from cmr import geometry as g
    from cmr.diagnose import PEAK_YAWS_DEG, peak_grid
    pose = level_camera()
    poses, dist, turn_zero = peak_grid(pose)
    assert len(poses) == 405 and turn_zero.sum() == 81
    centre = g.invert(pose)[:3, 3]
    moved = np.array([g.invert(p)[:3, 3] - centre for p in poses])
    assert np.allclose(moved[:, 2], 0.0, atol=1e-9) and np.allclose(np.linalg.norm(moved, axis=1), dist)
    assert dist.max() <= 5.0 + 1e-9 and sorted(set(np.round(dist ** 2, 6)))[:3] == [0.0, 1.0, 2.0]
    assert np.allclose(sorted(turn_deg(pose, p) for p in poses[::81]), sorted(PEAK_YAWS_DEG), atol=1e-6)
    # the untouched pose is on the grid, at distance 0, with the true heading
    assert any(np.allclose(p, pose) for p, z in zip(poses, turn_zero) if z)
