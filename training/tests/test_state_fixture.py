"""The PyTorch state builder must produce the observation the Rust server builds (fixtures/state.json)."""

import json
from pathlib import Path

import numpy as np
import torch

from cmr.models import COLUMN_SHIFTS, FEATURE_DIM, GRID_HEIGHT, GRID_WIDTH, ROW_SHIFTS, Agent
from cmr.state import alignment, build_state

FIXTURE = json.loads((Path(__file__).resolve().parents[2] / "fixtures" / "state.json").read_text())


def fixture_tensors():
    """(pose, points, intrinsics, point features, image features, frustum probs) as the Rust test builds them."""
    k = FIXTURE["intrinsics"]
    points = torch.tensor(FIXTURE["points_map"], dtype=torch.float32)[None]
    n = points.shape[1]
    features = torch.tensor(FIXTURE["point_features"], dtype=torch.float32).view(1, n, FEATURE_DIM)
    cells = GRID_HEIGHT * GRID_WIDTH
    image = (torch.arange(FEATURE_DIM * cells) % 7).float().mul(0.1).view(1, FEATURE_DIM, GRID_HEIGHT, GRID_WIDTH)
    probs = torch.tensor(FIXTURE["frustum_probs"], dtype=torch.float32)[None]
    pose = torch.tensor(FIXTURE["camera_from_map"], dtype=torch.float32)[None]
    kk = torch.tensor([[k["fx"], k["fy"], k["cx"], k["cy"]]], dtype=torch.float32)
    return pose, points, kk, features, image, probs


def test_state_matches_rust():
    pose, points, kk, features, image, probs = fixture_tensors()
    cells = GRID_HEIGHT * GRID_WIDTH
    state_2d, state_3d = build_state(pose, points, kk, features, image, probs)

    assert torch.equal(state_2d[0, :FEATURE_DIM], image[0])
    projected = state_2d[0, FEATURE_DIM:].reshape(FEATURE_DIM, cells)
    expected = np.zeros((FEATURE_DIM, cells), dtype=np.float32)
    for entry in FIXTURE["occupied_cells"]:
        expected[:, entry["cell"]] = entry["mean"]
    assert np.allclose(projected.numpy(), expected, atol=1e-5)
    assert np.allclose(state_3d[0].numpy().ravel(), FIXTURE["state_3d"], atol=1e-5)


def test_alignment_matches_rust():
    """The multi-start search's score: Rust's value for the fixture's pose (key `alignment`)."""
    pose, points, kk, features, image, _ = fixture_tensors()
    want = FIXTURE["alignment"]
    got = float(alignment(pose, points, kk, features, image)[0])
    assert abs(got - want) <= 1e-4 * abs(want), (got, want)


def test_correlation_matches_rust():
    """The correlation-form state (manifest `state_2d.form` = correlation): the server computes
    `Agent.correlate` in Rust (`agent::state::write_correlation`); key `correlation` holds its cells."""
    pose, points, kk, features, image, probs = fixture_tensors()
    stored = FIXTURE["correlation"]
    assert (tuple(stored["row_shifts"]), tuple(stored["column_shifts"])) == (ROW_SHIFTS, COLUMN_SHIFTS)
    state_2d, _ = build_state(pose, points, kk, features, image, probs)
    with torch.no_grad():
        volume = Agent().correlate(state_2d)[0].reshape(len(ROW_SHIFTS) + len(COLUMN_SHIFTS) + 1, -1).numpy()
    expected = np.zeros_like(volume)
    for entry in stored["cells"]:
        expected[:, entry["cell"]] = entry["values"]
    assert len(stored["cells"]) > 10
    assert np.allclose(volume, expected, atol=1e-5), np.abs(volume - expected).max()
