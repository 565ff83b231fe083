"""The inverse-dynamics ceilings (examples/measurements/idm_ceiling.py) on a real tiny build, a checkpoint and hand-made frames."""

import numpy as np
import pytest

from examples.measurements.idm_ceiling import (
    EMBEDDING_PARTS,
    OWN_INVERSE,
    PREDICTED,
    ceiling,
    embedding_ceiling,
    embedding_frames,
    load_frames,
)
from lerobot_jept.evaluation.prompt_probe import probe_frames
from lerobot_jept.policies.discretization import to_bin_indices
from tests.conftest import TINY, load
from tests.lerobot_jept.policies.test_policy import tiny_config
from tests.lerobot_jept.test_hub import checkpoint  # noqa: F401  (the saved tiny checkpoint, a fixture)


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


def test_embedding_frames_pair_the_label_with_the_states_and_embeddings_of_t_and_t1(checkpoint):  # noqa: F811
    cfg = tiny_config()  # the configuration the shared tiny checkpoint was made with
    frames = embedding_frames(str(checkpoint), "test/mw_tiny_demo", None, frames_per_episode=3)
    dataset = load("test/mw_tiny_demo")
    indices = probe_frames(dataset, 3)
    table = dataset.hf_dataset.with_format("numpy")
    state, action = table["observation.state"], table["action"]
    n, tokens, j = len(indices), cfg.frame_perceiver_queries + 1, cfg.joint_embedding_dim
    parts = frames["parts"]
    assert list(parts) == list(EMBEDDING_PARTS)
    assert parts["joint embedding"].shape == (n, 2 * tokens * j)
    assert parts["its self-state token"].shape == (n, 2 * j)
    assert parts["its visual tokens"].shape == (n, 2 * (tokens - 1) * j)
    expected = np.stack([np.concatenate([state[i], state[i + 1]]) for i in indices])
    np.testing.assert_allclose(parts["self-state"], expected, rtol=1e-6)
    assert (frames["y"] == np.stack([to_bin_indices(action[i], 7) for i in indices])).all()
    assert frames["predicted"].shape == (n, 2 * j)
    np.testing.assert_allclose(
        frames["predicted"][:, :j], parts["its self-state token"][:, :j]
    )  # the real h_t
    assert frames["own"].shape == (n, 4) and set(np.unique(frames["own"])) <= set(range(7))
    assert set(frames["task"]) == set(TINY["demo_tasks"])
    # the self-state token is the last of each frame's tokens
    h = parts["joint embedding"].reshape(n, 2, tokens, j)
    np.testing.assert_allclose(parts["its self-state token"], h[:, :, -1].reshape(n, -1))


def test_embedding_ceiling_scores_each_input_and_the_checkpoints_own_choice():
    rng = np.random.default_rng(0)
    motion = rng.normal(size=(300, 2))
    y = np.stack([np.where(motion[:, 0] > 0, 6, 0), np.full(300, 3)], 1)
    noise = rng.normal(size=(300, 8))

    def frames(rows, task):
        parts = {name: noise[rows] for name in EMBEDDING_PARTS}
        parts["self-state"] = parts["its self-state token"] = motion[rows]
        return {
            "parts": parts,
            "predicted": -motion[rows],  # a predicted next state that moves the other way
            "y": y[rows],
            "own": np.full((len(rows), 2), 3),
            "task": np.array([task] * len(rows)),
        }

    out = embedding_ceiling(frames(np.arange(250), "a"), frames(np.arange(250, 300), "b"))
    assert set(out) == {*EMBEDDING_PARTS, PREDICTED, OWN_INVERSE}
    # the state-token model is fitted on the real pairs and scored on the predicted ones
    assert out["its self-state token"]["b"]["whole"] >= 0.9 and out[PREDICTED]["b"]["whole"] <= 0.1
    assert out["self-state"]["b"]["whole"] >= 0.9
    assert out["its visual tokens"]["b"]["whole"] < 0.8  # noise tells the motion no better than chance
    own = out[OWN_INVERSE]["b"]
    assert own["per_dim"][1] == 1.0 and own["whole"] == pytest.approx(float((y[250:, 0] == 3).mean()))
