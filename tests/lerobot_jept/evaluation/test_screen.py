"""``jept-screen``'s smoothing of inverse dynamics' readings (``--smooth``), on hand-made frames."""

import numpy as np
import pytest

from lerobot_jept.evaluation.screen import main, majority, smoothed, state_ceiling


def test_majority_keeps_held_actions_and_overrules_a_lone_change():
    labels = np.array([[0, 3], [0, 3], [6, 3], [0, 3], [0, 2], [0, 2]])
    assert majority(labels, 1).tolist() == [[0, 3], [0, 3], [0, 3], [0, 3], [0, 2], [0, 2]]
    assert majority(labels, 0).tolist() == labels.tolist()


def test_smoothing_stays_within_each_episode():
    predicted = np.array([[1], [1], [5], [5], [5], [1]])
    episode = np.array([0, 0, 0, 1, 1, 1])
    # within episodes; across the boundary frame 2 would read 5 (its window: 1, 5, 5)
    assert smoothed(predicted, episode, 1)[:, 0].tolist() == [1, 1, 1, 5, 5, 5]
    assert smoothed(predicted, episode, 0).tolist() == predicted.tolist()


def test_smoothed_readings_are_what_the_screen_scores():
    """Perfect readings of labels that change every other frame: smoothing over one frame each side turns the
    lone changes into their neighbours' bin, and the score counts exactly the frames the majority leaves."""
    rng = np.random.default_rng(0)
    x = rng.normal(size=(600, 1))
    y = np.stack([np.where(x[:, 0] > 0, 6, 0)], 1)  # the action is the sign of the motion: readable exactly
    train = {"x": x, "y": y, "task": np.array(["a"] * 600), "episode": np.zeros(600, int)}
    probe_y = np.array([[0], [0], [6], [0], [0], [6], [6], [6], [0], [6]])
    probe_x = np.where(probe_y == 6, 2.0, -2.0)
    probe = {"x": probe_x, "y": probe_y, "task": np.array(["a"] * 10), "episode": np.array([0] * 5 + [1] * 5)}
    assert state_ceiling(train, probe, epochs=20)["a"]["whole"] == 1.0
    kept = (np.concatenate([majority(probe_y[:5], 1), majority(probe_y[5:], 1)]) == probe_y).mean()
    assert kept == 0.7
    assert state_ceiling(train, probe, epochs=20, smooth=1)["a"]["whole"] == pytest.approx(kept)


def test_screen_refuses_a_negative_smoothing_window():
    with pytest.raises(SystemExit, match="--smooth must be 0 or more"):
        main(["--probe_repo_id=test/p_probe", "--arms={d: [test/p_demo]}", "--smooth=-1"])
