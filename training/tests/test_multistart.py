"""The multi-start search: its starts, its per-iteration selection, and that it leaves the batch as it was."""

import math

import numpy as np
import pytest

from cmr import episodes as ep
from cmr import geometry as g

PRIOR = g.apply_action(np.array([[0, -1, 0, 0], [0, 0, -1, 1.5], [1, 0, 0, -0.3], [0, 0, 0, 1.0]]),
                       np.zeros(3), 10.0, 0.5, -2.0)
PIVOT = np.array([12.0, -3.0, 0.5])


def test_start_yaw_offsets():
    assert g.start_yaw_offsets(1) == [0.0]
    assert g.start_yaw_offsets(4) == [0.0, 90.0, 180.0, -90.0]
    assert g.start_yaw_offsets(8) == [0.0, 45.0, 90.0, 135.0, 180.0, -135.0, -90.0, -45.0]
    with pytest.raises(ValueError):
        g.start_yaw_offsets(0)


def test_starts_turn_the_prior_about_the_pivot():
    """Each start is the prior turned by exactly its offset about camera y through the pivot: the
    motion from the prior to it is that yaw with no shift of the pivot."""
    for off in g.start_yaw_offsets(4):
        start = g.apply_action(PRIOR, PIVOT, off, 0.0, 0.0)
        yaw, tx, tz = g.needed_motion(PRIOR, start, PIVOT)
        assert abs(math.remainder(yaw - off, 360.0)) < 1e-9 and abs(tx) < 1e-9 and abs(tz) < 1e-9
        assert abs(g.pose_error(start, PRIOR)["rre_geodesic_deg"] - abs(off)) < 1e-6


def test_selection_takes_the_best_hypothesis_per_iteration():
    scores = np.array([[[0.1, 0.5, 0.3], [0.2, 0.2, -1.0]],   # hypothesis 0, iterations 1-2, rows 0-2
                       [[0.4, 0.5, 0.2], [0.1, 0.2, -1.0]],
                       [[0.3, 0.1, 0.6], [0.2, 0.3, -1.0]]])
    assert ep.select_hypotheses(scores).tolist() == [[1, 0, 2], [0, 2, 0]]  # ties go to the lowest index


class FakeEpisodes:
    """Two rows; a pose's alignment is highest when its yaw matches the row's truth."""
    def __init__(self, truth_yaws, action_frame=g.CAMERA_Y):
        self.initial = [PRIOR.copy(), PRIOR.copy()]
        self.pivots = [PIVOT, PIVOT]
        self.action_frame = action_frame
        self.truth = [g.apply_action(PRIOR, PIVOT, y, 0.0, 0.0, frame=action_frame) for y in truth_yaws]

    def __len__(self):
        return 2

    def alignment(self, poses):
        return np.array([-g.pose_error(p, t)["rre_geodesic_deg"] for p, t in zip(poses, self.truth)])


@pytest.mark.parametrize("frame", g.ACTION_FRAMES)
def test_multi_start_answers_with_the_best_aligned_start(monkeypatch, frame):
    """With an agent that stands still, the answer is the start nearest the truth in yaw; hypothesis
    0 is the prior itself, and the batch's starts are restored afterwards."""
    def still(agent, episodes, steps, mode, keep_states=False):
        assert mode == "greedy" and not keep_states
        return ep.Trajectory([list(episodes.initial)] * (steps + 1), *[None] * 5)
    monkeypatch.setattr(ep, "rollout", still)
    eps = FakeEpisodes([100.0, -30.0], frame)
    prior = [p.copy() for p in eps.initial]
    selected, trajectories = ep.multi_start(None, eps, 3, 4)
    assert len(trajectories) == 4 and len(selected) == 3
    assert all(np.array_equal(a, b) for a, b in zip(eps.initial, prior))
    assert np.allclose(trajectories[0].poses[0][0], PRIOR, atol=1e-12)
    for poses in selected:
        assert np.allclose(poses[0], g.apply_action(PRIOR, PIVOT, 90.0, 0.0, 0.0, frame=frame))
        assert np.allclose(poses[1], PRIOR)
