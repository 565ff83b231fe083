"""Real-robot data: an SO-100-shaped recording (two cameras, joint state, 6-D absolute joint actions in degrees)
and action-free video of the same robot, written through LeRobot's own API, mixed with jept-mix, trained with
lerobot-train and run through LeRobot's rollout loop on a stand-in arm with a prompt video file."""

import logging

import numpy as np
import pytest
import torch
from lerobot.processor import TransitionKey

from lerobot_jept import JEPTConfig
from lerobot_jept.policies.discretization import bin_centres
from lerobot_jept.policies.jept.processor_jept import JeptActionBinsStep
from tests.conftest import write_clip
from tests.lerobot_jept.standinarm import CAMERAS, JOINTS, SENT

LOWS = np.array([-90.0, -100.0, -95.0, -80.0, -120.0, 0.0])
HIGHS = np.array([90.0, 100.0, 95.0, 80.0, 120.0, 100.0])


def write_arm_repo(repo_id: str, tasks: list[str], with_actions: bool, seed: int):
    """Episodes of the stand-in arm through LeRobot's own API: both cameras, joint state and (``with_actions``)
    the commanded joint angles in degrees, each joint over its own range."""
    from lerobot.datasets.lerobot_dataset import LeRobotDataset

    names = [f"{j}.pos" for j in JOINTS]
    image = {"dtype": "video", "shape": (32, 32, 3), "names": ["height", "width", "channels"]}
    features = {f"observation.images.{c}": image for c in CAMERAS}
    features["observation.state"] = {"dtype": "float32", "shape": (6,), "names": names}
    if with_actions:
        features["action"] = {"dtype": "float32", "shape": (6,), "names": names}
    ds = LeRobotDataset.create(
        repo_id=repo_id, fps=10, features=features, robot_type="so100_follower", use_videos=True
    )
    rng = np.random.default_rng(seed)
    for task in tasks:
        phase = rng.uniform(0, np.pi)
        for t in range(12):
            wave = 0.5 + 0.5 * np.sin(phase + np.linspace(0, 2 * np.pi, 12)[t] + np.arange(6))
            joints = (LOWS + wave * (HIGHS - LOWS)).astype(np.float32)
            frame = {
                f"observation.images.{c}": rng.integers(0, 256, (32, 32, 3), dtype=np.uint8) for c in CAMERAS
            }
            frame.update({"observation.state": joints, "task": task})
            if with_actions:
                frame["action"] = joints
            ds.add_frame(frame)
        ds.save_episode()
    ds.finalize()
    return ds


@pytest.fixture(scope="module")
def arm_repo():
    return write_arm_repo("test/arm_demos", ["pick up the cube", "pick up the cube"], True, 0)


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


def test_both_cameras_are_used(arm_repo):
    from lerobot.policies.factory import make_policy

    cfg = JEPTConfig.small(device="cpu", image_size=32, action_range="dataset")
    policy = make_policy(cfg, ds_meta=arm_repo.meta).eval()
    assert cfg.image_keys == ["observation.images.front", "observation.images.wrist"]
    frame = arm_repo[0]
    batch = {k: frame[k][None, None] for k in (*cfg.image_keys, "observation.state")}
    with torch.no_grad():
        both = policy.model.frame_tokens(policy.camera_frames(batch), batch["observation.state"])
        for camera in cfg.image_keys:
            changed = policy.model.frame_tokens(
                policy.camera_frames({**batch, camera: 1 - batch[camera]}), batch["observation.state"]
            )
            assert not torch.allclose(both, changed), camera  # each camera's frame reaches the tokens


def test_action_range_is_checked():
    with pytest.raises(ValueError, match="action_range must be one of"):
        JEPTConfig(action_range="auto")
    with pytest.raises(ValueError, match="both or neither"):
        JEPTConfig(action_lows=[0.0, 1.0], action_highs=[1.0])
    with pytest.raises(ValueError, match="dataset's statistics"):
        JEPTConfig(action_range="dataset").fit_action_range(None)
    assert bin_centres(3, [0.0, -10.0], [1.0, 10.0]).tolist() == [[0.0, 0.5, 1.0], [-10.0, 0.0, 10.0]]


@pytest.mark.slow
def test_mix_train_and_roll_out_on_the_arm_with_a_prompt_video_file(arm_repo, tmp_path, monkeypatch):
    import json
    import sys

    from lerobot.scripts.lerobot_rollout import rollout

    from lerobot_jept.datasets.mixing import MixConfig, run_mix
    from lerobot_jept.datasets.prompt_videos import PromptVideosConfig, make_prompt_bank
    from tests.lerobot_jept.test_end_to_end import CONFIG, run

    write_arm_repo("test/arm_videos", ["put the cube down"] * 2, with_actions=False, seed=1)
    run_mix(
        MixConfig(
            demo_repo_ids=["test/arm_demos"],
            video_repo_ids=["test/arm_videos"],
            output_repo_id="test/arm_mix",
        )
    )
    clips = tmp_path / "prompts"
    for seed, task in enumerate(("pick up the cube", "put the cube down")):
        (clips / task).mkdir(parents=True)
        frames = torch.randint(
            0, 256, (10, 3, 32, 32), dtype=torch.uint8, generator=torch.Generator().manual_seed(seed)
        )
        write_clip(frames, clips / task / "phone.mp4")
    make_prompt_bank(PromptVideosConfig(videos=str(clips), output_repo_id="test/arm_prompts", image_size=32))

    out = tmp_path / "train"
    log = run(
        [
            "lerobot-train",
            f"--config_path={CONFIG}",
            "--dataset.repo_id=test/arm_mix",
            "--policy.prompt_repo_id=test/arm_prompts",
            "--policy.image_size=32",
            "--policy.max_prompt_length=4",
            "--policy.action_range=dataset",
            "--steps=2",
            "--save_freq=2",
            "--batch_size=4",
            "--num_workers=0",
            f"--output_dir={out}",
        ],
        tmp_path,
    )
    assert "clipped" not in log
    model = out / "checkpoints/last/pretrained_model"
    config = json.loads((model / "config.json").read_text())
    assert {f"observation.images.{c}" for c in CAMERAS} <= set(config["input_features"])
    np.testing.assert_allclose(config["action_lows"], arm_repo.meta.stats["action"]["min"], rtol=1e-5)

    SENT.clear()
    monkeypatch.setattr(
        sys,
        "argv",
        [
            "lerobot-rollout",
            "--robot.type=jept_standin_arm",
            f"--policy.path={model}",
            f"--policy.prompt_video={clips / 'put the cube down' / 'phone.mp4'}",
            "--task=put the cube down",
            "--duration=4",
            "--fps=5",
            "--device=cpu",
            "--play_sounds=false",
            "--return_to_initial_position=false",
        ],
    )
    rollout()
    assert len(SENT) >= 2
    sent = np.array([[a[f"{j}.pos"] for j in JOINTS] for a in SENT])
    centres = bin_centres(7, config["action_lows"], config["action_highs"])  # (6 joints, 7 bins) in degrees
    assert (np.abs(sent[..., None] - centres[None]).min(-1) < 1e-3).all()  # each joint at one of its own bins
