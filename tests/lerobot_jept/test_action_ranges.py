"""Absolute actions (a real arm's joints in degrees): each dimension discretised over its own range in the data."""

import logging

import numpy as np
import pytest
import torch
from lerobot.processor import TransitionKey

from lerobot_jept import JEPTConfig
from lerobot_jept.discretization import bin_centres
from lerobot_jept.processor_jept import JeptActionBinsStep

JOINTS = ["shoulder_pan", "shoulder_lift", "elbow_flex", "wrist_flex", "wrist_roll", "gripper"]
LOWS = np.array([-90.0, -100.0, -95.0, -80.0, -120.0, 0.0])
HIGHS = np.array([90.0, 100.0, 95.0, 80.0, 120.0, 100.0])


@pytest.fixture(scope="module")
def arm_repo():
    """An SO-100-shaped recording through LeRobot's own API: one camera, joint state, 6-D joint actions in
    degrees, each joint over its own range."""
    from lerobot.datasets.lerobot_dataset import LeRobotDataset

    names = [f"{j}.pos" for j in JOINTS]
    features = {
        "observation.images.front": {
            "dtype": "video",
            "shape": (32, 32, 3),
            "names": ["height", "width", "channels"],
        },
        "observation.state": {"dtype": "float32", "shape": (6,), "names": names},
        "action": {"dtype": "float32", "shape": (6,), "names": names},
    }
    ds = LeRobotDataset.create(
        repo_id="test/arm_degrees", fps=30, features=features, robot_type="so100_follower", use_videos=True
    )
    rng = np.random.default_rng(0)
    for _ in range(2):
        phase = rng.uniform(0, np.pi)
        for t in range(12):
            wave = 0.5 + 0.5 * np.sin(phase + np.linspace(0, 2 * np.pi, 12)[t] + np.arange(6))
            action = (LOWS + wave * (HIGHS - LOWS)).astype(np.float32)
            image = rng.integers(0, 256, (32, 32, 3), dtype=np.uint8)
            ds.add_frame(
                {
                    "observation.images.front": image,
                    "observation.state": action,
                    "action": action,
                    "task": "pick",
                }
            )
        ds.save_episode()
    ds.finalize()
    return ds


def test_each_dimension_gets_its_own_range_from_the_data(arm_repo, caplog, tmp_path):
    from lerobot.configs.policies import PreTrainedConfig
    from lerobot.policies.factory import make_policy, make_pre_post_processors

    meta = arm_repo.meta
    cfg = JEPTConfig.small(device="cpu", image_size=32, action_range="dataset")
    policy = make_policy(cfg, ds_meta=meta)
    pre, _ = make_pre_post_processors(cfg, dataset_stats=meta.stats)
    np.testing.assert_allclose(cfg.action_lows, meta.stats["action"]["min"], rtol=1e-6)
    np.testing.assert_allclose(cfg.action_highs, meta.stats["action"]["max"], rtol=1e-6)
    assert policy.bin_centres.shape == (6, 7)

    actions = torch.stack([arm_repo[i]["action"] for i in range(len(arm_repo))])
    step = next(s for s in pre.steps if isinstance(s, JeptActionBinsStep))
    with caplog.at_level(logging.WARNING):
        bins = step({TransitionKey.ACTION: actions})[TransitionKey.ACTION]
    assert "clipped" not in caplog.text and step.num_clipped == 0
    assert bins.min() == 0 and bins.max() == 6  # each joint's extremes reach its end bins
    width = (torch.tensor(cfg.action_highs) - torch.tensor(cfg.action_lows)) / 6
    executed = policy.bin_actions(bins)
    assert (
        (executed - actions).abs() <= width / 2 + 1e-3
    ).all()  # the nearest centre of each joint's own bins

    cfg.save_pretrained(tmp_path)
    reloaded = PreTrainedConfig.from_pretrained(tmp_path)
    assert reloaded.action_lows == cfg.action_lows and reloaded.action_highs == cfg.action_highs

    fixed = JeptActionBinsStep(7, -1.0, 1.0)  # the default [-1, 1] clips degrees, and says what to do
    with caplog.at_level(logging.WARNING):
        fixed({TransitionKey.ACTION: actions})
    assert "--policy.action_range=dataset" in caplog.text


def test_action_range_is_checked():
    with pytest.raises(ValueError, match="action_range must be one of"):
        JEPTConfig(action_range="auto")
    with pytest.raises(ValueError, match="both or neither"):
        JEPTConfig(action_lows=[0.0, 1.0], action_highs=[1.0])
    with pytest.raises(ValueError, match="dataset's statistics"):
        JEPTConfig(action_range="dataset").fit_action_range(None)
    assert bin_centres(3, [0.0, -10.0], [1.0, 10.0]).tolist() == [[0.0, 0.5, 1.0], [-10.0, 0.0, 10.0]]
