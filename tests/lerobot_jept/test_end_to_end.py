"""End to end with LeRobot's own entry points: lerobot-train, lerobot-eval and jept-eval-suite as subprocesses,
and the jept_metaworld env against the builder's data."""

import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch
from lerobot.configs.types import FeatureType
from lerobot.envs.factory import make_env
from lerobot.envs.utils import env_to_policy_features, preprocess_observation
from lerobot.utils.feature_utils import dataset_to_policy_features

from lerobot_jept.envs.configs import JeptMetaworldEnvConfig
from tests.conftest import load, write_clip

BIN = Path(sys.executable).parent
MIX, PROMPTS = "test/mw_tiny_mix", "test/mw_tiny_prompts"
CONFIG = Path(__file__).parents[2] / "examples/configs/train_jept_small_cpu.json"
TINY_TRAIN = ["--batch_size=4", "--num_workers=0", "--policy.max_prompt_length=4", "--log_freq=2"]


def run(args: list[str], cwd: Path, ok: bool = True) -> str:
    """Run one of the venv's commands; it must succeed (``ok``) or fail. Returns its output."""
    proc = subprocess.run(
        [str(BIN / args[0]), *args[1:]], cwd=cwd, capture_output=True, text=True, env=os.environ.copy()
    )
    if ok:
        assert proc.returncode == 0, f"{args[0]} failed:\n{proc.stdout[-3000:]}\n{proc.stderr[-5000:]}"
    else:
        assert proc.returncode != 0, f"{args[0]} should have failed"
    return proc.stdout + proc.stderr


def lerobot_eval(
    model: Path,
    out: Path,
    cwd: Path,
    prompts: str = PROMPTS,
    episodes: int = 1,
    steps: int = 10,
    prompt: list[str] | None = None,
) -> dict:
    """``lerobot-eval`` of a checkpoint on the unseen handle-press-v3 of the tiny build; its eval_info.json.
    The env shows the bank ``prompts``' videos unless ``prompt`` gives other flags."""
    if prompt is None:
        prompt = [f"--env.prompt_repo_id={prompts}", "--env.prompt_max_frames=4"]
    run(
        [
            "lerobot-eval",
            f"--policy.path={model}",
            "--env.type=jept_metaworld",
            "--env.task=handle-press-v3",
            "--env.image_size=64",
            f"--env.episode_length={steps}",
            *prompt,
            f"--eval.n_episodes={episodes}",
            f"--eval.batch_size={episodes}",
            "--policy.device=cpu",
            f"--output_dir={out}",
        ],
        cwd,
    )
    return json.loads((out / "eval_info.json").read_text())


def train(tmp: Path, repo: str, steps: int, *extra: str) -> tuple[Path, str]:
    out = tmp / f"train_{repo.split('/')[-1]}"
    log = run(
        [
            "lerobot-train",
            f"--config_path={CONFIG}",
            f"--dataset.repo_id={repo}",
            f"--policy.prompt_repo_id={PROMPTS}",
            f"--steps={steps}",
            f"--save_freq={steps}",
            f"--output_dir={out}",
            *TINY_TRAIN,
            *extra,
        ],
        tmp,
    )
    return out, log


@pytest.fixture(scope="module")
def trained(tiny_build, tmp_path_factory):
    tmp = tmp_path_factory.mktemp("e2e")
    out, log = train(tmp, MIX, 4, "--policy.prompt_warmup_steps=2", "--policy.phase_steps=2")
    return tmp, out, log


@pytest.mark.slow
def test_lerobot_train_logs_both_losses_and_checkpoints(trained):
    _, out, log = trained
    assert "loss_obs:" in log and "loss_act:" in log and "labelled_fraction:" in log
    model = out / "checkpoints/last/pretrained_model"
    for name in ("config.json", "model.safetensors", "train_config.json", "policy_preprocessor.json"):
        assert (model / name).is_file(), name
    assert json.loads((model / "config.json").read_text())["type"] == "jept"


@pytest.mark.slow
def test_training_resumes(trained):
    tmp, out, _ = trained
    log = run(
        [
            "lerobot-train",
            f"--config_path={out}/checkpoints/last/pretrained_model/train_config.json",
            "--resume=true",
            "--steps=6",
        ],
        tmp,
    )
    assert "Resum" in log or "resum" in log
    assert (out / "checkpoints/000006/pretrained_model/model.safetensors").is_file()


@pytest.mark.slow
def test_lerobot_train_moves_the_weight_average_every_step_and_resumes_it(tiny_build, tmp_path):
    """``--policy.weight_ema_decay`` through LeRobot's own loop: after every optimizer step the average moves
    towards the trained weights with the warm-up decay, across a ``--resume=true``, and lerobot-eval runs on it."""
    from safetensors.torch import load_file

    out, _ = train(tmp_path, MIX, 2, "--policy.weight_ema_decay=0.5", "--save_freq=1")
    run(
        [
            "lerobot-train",
            f"--config_path={out}/checkpoints/last/pretrained_model/train_config.json",
            "--resume=true",
            "--steps=4",
        ],
        tmp_path,
    )
    states = [
        load_file(out / f"checkpoints/00000{k}/pretrained_model/model.safetensors") for k in (1, 2, 3, 4)
    ]
    averaged = [k for k in states[0] if k.startswith("weight_average.")]
    assert len(averaged) > 100
    for k in range(2, 5):  # checkpoint k: the trained weights after step k and their average
        decay = min(0.5, k / (9 + k))  # optimizer step k is update n = k - 1: (1 + n) / (10 + n)
        before, now = states[k - 2], states[k - 1]
        for key in averaged:
            trained = now["model." + key.removeprefix("weight_average.").replace("__", ".")]
            torch.testing.assert_close(now[key], decay * before[key] + (1 - decay) * trained)
    assert any(not torch.equal(states[3][k], states[2][k]) for k in averaged)
    info = lerobot_eval(out / "checkpoints/last/pretrained_model", tmp_path / "eval", tmp_path, steps=5)
    assert info["overall"]["n_episodes"] == 1


@pytest.mark.slow
def test_action_chunks_through_lerobot_train_and_lerobot_eval(tiny_build, tmp_path):
    """``--policy.chunk_size`` trains through LeRobot's loop and is saved; lerobot-eval executes the chunks, takes
    ``--policy.n_action_steps`` as a control setting and refuses one longer than the chunk."""
    out, _ = train(tmp_path, MIX, 2, "--policy.chunk_size=2", "--policy.n_action_steps=2")
    model = out / "checkpoints/last/pretrained_model"
    saved = json.loads((model / "config.json").read_text())
    assert (saved["chunk_size"], saved["n_action_steps"]) == (2, 2)
    assert lerobot_eval(model, tmp_path / "eval", tmp_path, steps=5)["overall"]["n_episodes"] == 1
    extra = ["--env.prompt_repo_id=" + PROMPTS, "--env.prompt_max_frames=4", "--policy.n_action_steps=1"]
    assert (
        lerobot_eval(model, tmp_path / "eval1", tmp_path, steps=5, prompt=extra)["overall"]["n_episodes"] == 1
    )
    log = run(
        ["lerobot-eval", f"--policy.path={model}", "--policy.n_action_steps=3", "--env.type=jept_metaworld"],
        tmp_path,
        ok=False,
    )
    assert "n_action_steps must be in [1, chunk_size] = [1, 2]" in log


@pytest.mark.slow
@pytest.mark.parametrize("repo, labelled", [("test/mw_tiny_demo", True), ("test/mw_tiny_video", False)])
def test_trains_on_demos_alone_and_on_videos_alone(tiny_build, tmp_path, repo, labelled):
    extra = [] if labelled else ["--policy.action_dim=4"]
    _, log = train(tmp_path, repo, 2, "--log_freq=1", *extra)
    fractions = {float(part.split(":")[1]) for part in log.split() if part.startswith("labelled_fraction:")}
    assert fractions and (min(fractions) > 0.5 if labelled else fractions == {0.0})


@pytest.mark.slow
def test_lerobot_eval_reports_success_and_writes_videos(trained):
    tmp, out, _ = trained
    eval_dir = tmp / "eval"
    info = lerobot_eval(out / "checkpoints/last/pretrained_model", eval_dir, tmp, episodes=2, steps=20)
    assert info["overall"]["n_episodes"] == 2
    assert 0.0 <= info["overall"]["pc_success"] <= 100.0
    assert len(list((eval_dir / "videos").rglob("*.mp4"))) == 2


@pytest.mark.slow
def test_lerobot_eval_takes_the_prompt_from_a_video_file(trained):
    """No prompt from the env: ``--policy.prompt_video`` reaches the saved policy, and so does
    ``--policy.prompt_repo_id`` (a bank that does not exist fails by its name, so it was the one used)."""
    from lerobot_jept.policies.prompts import PromptBank

    tmp, out, _ = trained
    model = out / "checkpoints/last/pretrained_model"
    assert "root" not in json.loads((model / "policy_preprocessor.json").read_text())["steps"][2]["config"]
    bank = PromptBank(PROMPTS, None, 1000, 64)
    clip = tmp / "clip.mp4"
    write_clip(bank.video(bank.episodes("Press a handle down")[0]), clip)
    info = lerobot_eval(model, tmp / "eval_clip", tmp, prompt=[f"--policy.prompt_video={clip}"], steps=5)
    assert info["overall"]["n_episodes"] == 1
    proc = subprocess.run(
        [
            str(BIN / "lerobot-eval"),
            f"--policy.path={model}",
            "--env.type=jept_metaworld",
            "--env.task=handle-press-v3",
            "--env.image_size=64",
            "--env.episode_length=5",
            "--eval.n_episodes=1",
            "--eval.batch_size=1",
            "--policy.device=cpu",
            "--policy.prompt_repo_id=test/no_such_prompts",
            f"--output_dir={tmp / 'eval_missing_bank'}",
        ],
        cwd=tmp,
        capture_output=True,
        text=True,
    )
    assert proc.returncode != 0 and "test/no_such_prompts" in proc.stdout + proc.stderr


@pytest.mark.slow
def test_eval_suite_writes_table_and_chart(trained):
    tmp, out, _ = trained
    suite = tmp / "suite"
    log = run(
        [
            "jept-eval-suite",
            f"--policy.path={out}/checkpoints/last/pretrained_model",
            f"--dataset.repo_id={MIX}",
            "--n_episodes=1",
            "--batch_size=1",
            f"--output_dir={suite}",
        ],
        tmp,
    )
    results = json.loads((suite / "results.json").read_text())
    probe = results["prompt_probe"]  # on the build's probe repo: one held-out episode of every task
    assert probe["dataset"] == "test/mw_tiny_probe"
    assert probe["prompt_separability"]["num_prompts"] == 4
    assert probe["prompt_separability"]["trained_tasks"]["num_prompts"] == 3  # the unseen task's left out
    assert set(probe["actions"]) == {"button-press-v3", "reach-v3", "drawer-close-v3", "handle-press-v3"}
    for row in probe["actions"].values():
        assert 0 <= row["control_whole"] <= row["control_per_dim"] <= 1
        assert 0 <= row["inverse_whole"] <= row["inverse_per_dim"] <= 1 and row["loss_obs"] > 0
    assert list(probe["splits"]) == ["T_demo", "T_vid", "T_unseen"]
    assert (
        probe["splits"]["T_vid"]["control_per_dim"] == probe["actions"]["drawer-close-v3"]["control_per_dim"]
    )
    assert "Prompt embedding E_prt" in (suite / "results.md").read_text()
    assert "| T_unseen | 1 |" in (suite / "results.md").read_text()
    assert (suite / "prompt_probe.json").is_file()
    assert set(results["per_task"]) == {"button-press-v3", "reach-v3", "drawer-close-v3", "handle-press-v3"}
    assert list(results["table"]) == ["T_demo", "T_vid", "handle-press-v3", "Seen average", "Unseen average"]
    assert all(0 <= v <= 100 for v in results["table"].values())
    assert (suite / "results.png").stat().st_size > 1000
    assert "| T_demo |" in (suite / "results.md").read_text() and "| T_demo |" in log


@pytest.mark.slow
def test_eval_suite_picks_up_the_tasks_it_finished_under_the_same_settings(trained):
    tmp, out, _ = trained
    suite = tmp / "suite_resume"
    args = [
        "jept-eval-suite",
        f"--policy.path={out}/checkpoints/last/pretrained_model",
        f"--dataset.repo_id={MIX}",
        "--n_episodes=1",
        "--batch_size=1",
        "--episode_length=10",
        "--splits=[video]",
        "--probe=false",
        f"--output_dir={suite}",
    ]
    info = suite / "tasks/drawer-close-v3/eval_info.json"

    def evaluated(*extra: str) -> tuple[int, dict]:
        run([*args, *extra], tmp)
        return info.stat().st_mtime_ns, json.loads((suite / "results.json").read_text())["per_task"]

    first, results = evaluated()
    again, reused = evaluated()
    # the same settings: the finished task is not rolled out again
    assert again == first and reused == results
    moved, _ = evaluated("--seed=7")
    assert moved != first  # other env seeds: evaluated again
    stamp = json.loads((suite / "tasks/drawer-close-v3/suite_task.json").read_text())
    assert stamp["settings"]["seed"] == 7 and stamp["settings"]["prompt_task"] is None
    assert len(stamp["settings"]["weights"]) == 64  # the checkpoint's weights by their hash, not its path


def test_env_features_match_the_dataset(tiny_build):
    env_cfg = JeptMetaworldEnvConfig(task="handle-press-v3", image_size=64)
    env_features = env_to_policy_features(env_cfg)
    ds_features = dataset_to_policy_features(load(MIX).meta.features)
    # the mix's label marker is training data for the preprocessor, not an observation the env gives
    assert ds_features.pop("observation.action_labelled").type is FeatureType.STATE
    assert env_features == ds_features
    assert {k for k, f in env_features.items() if f.type is FeatureType.VISUAL} == {"observation.image"}


def test_env_observation_matches_a_builder_frame(tiny_build):
    """A reset of the lerobot-eval env, through LeRobot's observation conversion, against the recorded frame
    of the same seed: keys, shapes, dtypes, value ranges, orientation."""
    home = Path(os.environ["HF_LEROBOT_HOME"])
    shard = json.loads((home / "test/mw_tiny.build/shards/demo/button-press-v3/0000/shard.json").read_text())
    env_cfg = JeptMetaworldEnvConfig(task="button-press-v3", image_size=64, prompt_repo_id=PROMPTS)
    vec = make_env(env_cfg, n_envs=1)["button-press-v3"][0]
    raw, _ = vec.reset(seed=[shard["seeds"][0]])
    vec.close()
    obs = preprocess_observation(raw)
    frame = load("test/mw_tiny_demo")[0]
    for key in ("observation.image", "observation.state"):
        assert obs[key].shape[1:] == frame[key].shape and obs[key].dtype == frame[key].dtype == torch.float32
    image, recorded = obs["observation.image"][0], frame["observation.image"]
    assert image.min() >= 0 and image.max() <= 1
    err = (image - recorded).abs().mean()
    assert err < 0.06 and (image.flip(1, 2) - recorded).abs().mean() > 3 * err  # same picture, upright
    torch.testing.assert_close(obs["observation.state"][0], frame["observation.state"])
    # the prompt crosses once per episode: the env's processor attaches it on the first step only
    assert "observation.prompt_video" not in obs and obs["observation.prompt_new"].item() == 1
    env_pre, _ = env_cfg.get_env_processors()
    first = env_pre(obs)
    video = first["observation.prompt_video"]
    assert video.shape[0] == 1 and 1 < video.shape[1] <= 250 and video.shape[2:] == (3, 64, 64)
    assert (
        first["observation.prompt_video"].dtype == torch.uint8
        and first["observation.prompt_video_mask"].all()
    )
    later = env_pre({**obs, "observation.prompt_new": torch.zeros(1, 1)})
    assert "observation.prompt_video" not in later and "observation.prompt_episode" not in later


def test_prompt_choice_is_deterministic_per_seed(tiny_build):
    env_cfg = JeptMetaworldEnvConfig(
        task="handle-press-v3", image_size=64, prompt_repo_id=PROMPTS, prompt_max_frames=4
    )
    env = env_cfg.make_prompted("handle-press-v3")
    chosen = {}
    for seed in (0, 1, 2, 3, 0, 1):
        obs, _ = env.reset(seed=seed)
        assert obs["prompt_episode"][0] == env.prompt_episode and obs["prompt_new"][0] == 1
        chosen.setdefault(seed, []).append((env.prompt_episode, env.prompt_video().copy()))
        assert env.step(np.zeros(4, np.float32))[0]["prompt_new"][0] == 0
    env.close()
    for picks in chosen.values():
        assert all(p[0] == picks[0][0] for p in picks)
        assert all(np.array_equal(p[1], picks[0][1]) for p in picks)
    assert {picks[0][0] for picks in chosen.values()} == set(env.episodes)  # both prompts in use
    assert chosen[0][0][0] == chosen[2][0][0] != chosen[1][0][0]  # prompt = seed % num_prompts


def test_prompt_task_shows_another_tasks_prompt_videos(tiny_build):
    """--env.prompt_task: the env runs its own task and shows, per seed, the prompt the other task's env shows."""
    fields = dict(image_size=64, prompt_repo_id=PROMPTS, prompt_max_frames=4)
    shown = JeptMetaworldEnvConfig(task="button-press-v3", prompt_task="reach-v3", **fields)
    env = shown.make_prompted("button-press-v3")
    reach = JeptMetaworldEnvConfig(task="reach-v3", **fields).make_prompted("reach-v3")
    own = JeptMetaworldEnvConfig(task="button-press-v3", **fields).make_prompted("button-press-v3")
    try:
        assert env.episodes == reach.episodes and set(env.episodes).isdisjoint(own.episodes)
        for seed in (0, 1):
            obs, _ = env.reset(seed=seed)
            reach.reset(seed=seed)
            assert obs["prompt_episode"] == reach.prompt_episode
            assert np.array_equal(env.prompt_video(), reach.prompt_video())
            assert env.unwrapped.task == "button-press-v3"  # the scene and success are the env task's
            assert np.array_equal(obs["pixels"], own.reset(seed=seed)[0]["pixels"])
    finally:
        for e in (env, reach, own):
            e.close()
    with pytest.raises(ValueError, match="--env.prompt_repo_id"):
        JeptMetaworldEnvConfig(task="button-press-v3", prompt_task="reach-v3", image_size=64)
    with pytest.raises(ValueError, match="reach-v3"):
        JeptMetaworldEnvConfig(task="button-press-v3", prompt_task="reach-v9", **fields)


def test_stock_metaworld_env_gets_a_clear_message(trained):
    from lerobot.configs.policies import PreTrainedConfig
    from lerobot.envs.configs import MetaworldEnv

    from lerobot_jept import JEPTPolicy

    _, out, _ = trained
    path = out / "checkpoints/last/pretrained_model"
    policy = JEPTPolicy.from_pretrained(path, config=PreTrainedConfig.from_pretrained(path))
    stock = env_to_policy_features(MetaworldEnv(task="handle-press-v3"))
    batch = {
        "observation.image": torch.rand(1, 3, 480, 480),
        "observation.state": torch.zeros(1, stock["observation.state"].shape[0]),
        "observation.prompt_video": torch.rand(1, 2, 3, 64, 64),
    }
    with pytest.raises(ValueError, match=r"observation.state.*18.*jept_metaworld"):
        policy.select_action(batch)


def test_prompt_probe_needs_a_labelled_repo(trained):
    tmp, out, _ = trained
    proc = subprocess.run(
        [
            str(BIN / "jept-prompt-probe"),
            f"--policy.path={out}/checkpoints/last/pretrained_model",
            "--dataset.repo_id=test/mw_tiny_video",
        ],
        cwd=tmp,
        capture_output=True,
        text=True,
    )
    assert proc.returncode != 0
    assert "has no `action`" in proc.stderr and "--demo_tasks" in proc.stderr
