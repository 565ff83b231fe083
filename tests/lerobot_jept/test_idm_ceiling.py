"""The state inverse-dynamics ceiling (scripts/idm_ceiling.py) on a real tiny build and on hand-made frames."""

import numpy as np
import pytest

from scripts.idm_ceiling import ceiling, load_frames
from tests.conftest import TINY, load


def test_frames_pair_each_action_with_the_next_state_change(tiny_build):
    frames = load_frames("test/mw_tiny_demo", None, steps=2, num_bins=7)
    dataset = load("test/mw_tiny_demo")
    episodes = dataset.meta.total_episodes
    assert len(frames["x"]) == dataset.meta.total_frames - 2 * episodes
    assert set(frames["task"]) == set(TINY["demo_tasks"])  # builder names, from the build metadata
    first = dataset.hf_dataset.with_format("numpy")[:3]
    state, action = first["observation.state"], first["action"]
    assert np.allclose(frames["x"][0], np.concatenate([state[1] - state[0], state[2] - state[1]]))
    assert (frames["y"][0] == np.rint((np.clip(action[0], -1, 1) + 1) * 3)).all()  # 7 bins over [-1, 1]
    with pytest.raises(ValueError, match="test/mw_tiny_video has no `action` column"):
        load_frames("test/mw_tiny_video", None, steps=1, num_bins=7)


def test_ceiling_counts_support_and_scores_per_task():
    rng = np.random.default_rng(0)
    x = rng.normal(size=(400, 2))
    y = np.stack([np.where(x[:, 0] > 0, 6, 0), np.full(400, 3)], 1)  # dim 0 from the motion, dim 1 constant
    demo = {"x": x, "y": y, "task": np.array(["a"] * 400)}
    probe_y = y[:20].copy()
    probe_y[10:, 1] = 5  # task "b": a whole action the demos never show
    probe = {"x": x[:20], "y": probe_y, "task": np.array(["a"] * 10 + ["b"] * 10)}
    out = ceiling(demo, probe)
    assert out["a"] == {"frames": 10, "in_demo_support": 1.0, "whole": 1.0, "per_dim": [1.0, 1.0]}
    assert out["b"]["in_demo_support"] == 0.0
    assert out["b"]["whole"] == 0.0 and out["b"]["per_dim"] == [1.0, 0.0]


def test_pixel_frames_stack_the_next_frame_on_the_channels(tiny_build):
    frames = load_frames("test/mw_tiny_demo", None, steps=1, num_bins=7, features="pixels")
    dataset = load("test/mw_tiny_demo")
    assert len(frames["x"]) == dataset.meta.total_frames - dataset.meta.total_episodes
    size = dataset.meta.features["observation.image"]["shape"][0]
    assert frames["x"].shape[1:] == (6, size, size) and frames["x"].dtype == np.uint8
    first = [(dataset[i]["observation.image"].numpy() * 255).round() for i in (0, 1)]
    assert np.array_equal(frames["x"][0], np.concatenate(first).astype(np.uint8))


def test_pixel_ceiling_reads_the_motion_between_frames():
    """A square that moves left (bin 0) or right (bin 6) from a random place: only the pair of frames tells
    which, and the CNN must read it on held-out pairs; the second dimension never moves."""
    rng = np.random.default_rng(0)

    def pairs(n):
        x = np.full((n, 6, 16, 16), 90, dtype=np.uint8)
        direction = rng.integers(0, 2, n)
        for i, (pos, right) in enumerate(zip(rng.integers(3, 10, n), direction, strict=True)):
            x[i, :3, 5:10, pos : pos + 4] = 255
            x[i, 3:, 5:10, pos + (2 if right else -2) : pos + (6 if right else 2)] = 255
        y = np.stack([direction * 6, np.full(n, 3)], 1)
        return x, y

    x, y = pairs(600)
    x_test, y_test = pairs(100)
    out = ceiling(
        {"x": x, "y": y, "task": np.array(["a"] * 600)},
        {"x": x_test, "y": y_test, "task": np.array(["a"] * 100)},
        features="pixels",
        epochs=15,
    )
    assert out["a"]["whole"] >= 0.95, out
