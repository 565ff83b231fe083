"""The robosuite builder, env and experts on the real simulator, at tiny sizes."""

import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from dataset_builders.core import build, rollout_expert
from dataset_builders.expert_rates import expert_successes
from dataset_builders.expert_rates import main as expert_rates_main
from dataset_builders.robosuite import RobosuiteBuildConfig, RobosuiteSimulator, main
from lerobot_jept.envs.robosuite import ARMS, STATE_DIM, JeptRobosuiteEnv
from tests.conftest import load

RS_TINY = dict(
    demo_tasks=["panda-stack"],
    video_tasks=["sawyer-square"],
    unseen_tasks=["ur5e-lift"],
    episodes_per_task=2,
    prompts_per_task=1,
    probe_episodes_per_task=0,
    image_size=64,
    episodes_per_shard=2,
)


@pytest.fixture(scope="module")
def rs_build():
    cfg = RobosuiteBuildConfig(repo_id="test/rs_tiny", **RS_TINY)
    return cfg, build(cfg, RobosuiteSimulator())


def test_repo_schemas(rs_build):
    for role, episodes in {"demo": 2, "video": 2, "prompts": 3, "mix": 4}.items():
        ds = load(f"test/rs_tiny_{role}")
        assert ds.meta.total_episodes == episodes
        assert ds.meta.fps == 20 and ds.meta.robot_type == "panda"
        assert ds.meta.features["observation.state"]["shape"] in ([STATE_DIM], (STATE_DIM,))
        has_action = role in ("demo", "mix")
        assert ("action" in ds.meta.features) == has_action
        if has_action:
            assert tuple(ds.meta.features["action"]["shape"]) == (7,)
    build_meta = json.loads((Path(load("test/rs_tiny_mix").root) / "meta/jept_build.json").read_text())
    assert build_meta["split"] == {
        "demo": ["panda-stack"],
        "video": ["sawyer-square"],
        "unseen": ["ur5e-lift"],
    }
    assert build_meta["protocol"]["simulator"] == "robosuite"


def test_prompts_show_the_prompt_arm_and_demos_the_panda(rs_build):
    prompts, demo = load("test/rs_tiny_prompts"), load("test/rs_tiny_demo")
    tasks = {prompts.meta.episodes[e]["tasks"][0]: e for e in range(prompts.meta.total_episodes)}
    ur5e = prompts[prompts.meta.episodes[tasks["lift (prompted by UR5e)"]]["dataset_from_index"]]
    panda = demo[0]
    # UR5e has 6 joints: the 7th joint slots of its state are zero-padded; the Panda uses all 7
    assert ur5e["observation.state"][6] == 0 and ur5e["observation.state"][13] == 0
    assert panda["observation.state"][6] != 0


def test_first_frame_matches_env_reset(rs_build):
    home = Path(os.environ["HF_LEROBOT_HOME"])
    shard = json.loads((home / "test/rs_tiny.build/shards/demo/panda-stack/0000/shard.json").read_text())
    frame = load("test/rs_tiny_demo")[0]
    env = JeptRobosuiteEnv("panda-stack", image_size=64)
    obs, _ = env.reset(seed=shard["seeds"][0])
    env.close()
    image = frame["observation.image"].permute(1, 2, 0).numpy() * 255
    assert image.std() > 10
    err = np.abs(image - obs["pixels"]).mean()
    assert err < 15 and np.abs(image - obs["pixels"][::-1]).mean() > 2 * err  # same picture, upright
    np.testing.assert_allclose(frame["observation.state"].numpy(), obs["agent_pos"], rtol=1e-5, atol=1e-6)


def test_same_seed_same_episode():
    env = JeptRobosuiteEnv("panda-lift", image_size=32)
    first = [env.reset(seed=3)[0]["agent_pos"] for _ in range(2)]
    other = env.reset(seed=4)[0]["agent_pos"]
    env.close()
    np.testing.assert_array_equal(first[0], first[1])
    assert not np.array_equal(first[0], other)


EXPERT_CASES = [(arm, m) for m in ("lift", "stack", "square", "can") for arm in sorted(ARMS)]


@pytest.fixture(scope="module")
def expert_outcomes() -> dict[str, list[bool]]:
    """Every (arm, manipulation) expert on seeds 0-9, two tasks at a time (as ``expert_rates --num_workers=2``)."""
    import multiprocessing as mp
    from concurrent.futures import ProcessPoolExecutor

    from dataset_builders.record import worker_init

    tasks = [f"{arm}-{m}" for arm, m in EXPERT_CASES]
    with ProcessPoolExecutor(2, mp_context=mp.get_context("spawn"), initializer=worker_init) as pool:
        return dict(zip(tasks, pool.map(expert_successes, tasks, [range(10)] * len(tasks)), strict=True))


@pytest.mark.slow
@pytest.mark.parametrize("arm, manipulation", EXPERT_CASES)
def test_expert_succeeds_on_every_arm(expert_outcomes, arm, manipulation):
    """Scripted experts with 7-bin actions, on the arm that records the prompts: >= 90% of seeded episodes."""
    successes = sum(expert_outcomes[f"{arm}-{manipulation}"])
    assert successes >= 9, f"{arm}-{manipulation}: {successes}/10"


def test_sawyer_base_joint_turns():
    """robosuite's Sawyer model rests link 0 on its base; with that contact the base joint barely turns."""
    env = JeptRobosuiteEnv("sawyer-can", image_size=32, embodiment="prompt")
    env.reset(seed=0)
    for _ in range(20):
        obs, *_ = env.step(np.array([0, -1, 0, 0, 0, 0, -1], np.float32))  # sideways, towards the can's bin
    env.close()
    base_joint = obs["agent_pos"][0]
    assert base_joint < -0.1, base_joint


def test_expert_success_without_frames_is_the_rendered_episode():
    """``expert_succeeds`` (what the expert test and ``expert_rates`` measure) replays the episode that ``step``
    records: same outcome, same length, same final state."""
    env = JeptRobosuiteEnv("sawyer-lift", image_size=32, embodiment="prompt")
    _, success = rollout_expert(env, 3, 7)  # the builder's rollout, frames rendered
    rendered = (success, env._steps, env._state())
    assert env.expert_succeeds(3) == rendered[0]
    assert env._steps == rendered[1]
    np.testing.assert_array_equal(env._state(), rendered[2])
    env.close()


def test_expert_rates_command(capsys):
    expert_rates_main(["--tasks=[panda-lift]", "--episodes=2", "--seed=5"])
    assert "expert success, seeds 5-6:\npanda-lift: 2/2" in capsys.readouterr().out
    expert_rates_main(["--tasks=[ur5e-lift, panda-lift]", "--episodes=2", "--seed=5", "--num_workers=2"])
    assert (
        "expert success, seeds 5-6:\nur5e-lift: 2/2\npanda-lift: 2/2" in capsys.readouterr().out
    )  # task order
    with pytest.raises(SystemExit, match="Unknown robosuite task 'panda-lfit'.*panda-lift"):
        expert_rates_main(["--tasks=[panda-lfit]"])
    with pytest.raises(SystemExit, match="--num_workers=0: use 1 or more"):
        expert_rates_main(["--num_workers=0"])


def test_bad_flags(tmp_path, capsys):
    with pytest.raises(SystemExit, match="Unknown robosuite task 'panda-stak'.*panda-stack"):
        main(["--repo_id=x/y", "--demo_tasks=[panda-stak]", f"--root={tmp_path}"])
    with pytest.raises(SystemExit, match="--action_repeat=1"):
        main(["--repo_id=x/y", "--action_repeat=2", f"--root={tmp_path}"])


@pytest.mark.slow
@pytest.mark.parametrize("policy_type", ["jept", "dt_star", "vid2robot", "idm"])
def test_train_and_eval_end_to_end(rs_build, tmp_path, policy_type):
    """Every policy type trains on the robosuite mix; jept also evaluates through lerobot-eval and the suite
    (the baselines' evaluation goes through the same env code, tested on Meta-World)."""
    bin_dir = Path(sys.executable).parent
    config = Path(__file__).parents[2] / f"examples/configs/train_{policy_type}_small_cpu.json"
    prompt = (
        []
        if policy_type == "idm"
        else ["--policy.prompt_repo_id=test/rs_tiny_prompts", "--policy.max_prompt_length=4"]
    )
    commands = [
        [
            "lerobot-train",
            f"--config_path={config}",
            "--dataset.repo_id=test/rs_tiny_mix",
            *prompt,
            "--policy.image_size=64",
            "--steps=2",
            "--batch_size=2",
            "--num_workers=0",
            f"--output_dir={tmp_path / 'train'}",
        ],
        [
            "lerobot-eval",
            f"--policy.path={tmp_path / 'train/checkpoints/last/pretrained_model'}",
            "--env.type=jept_robosuite",
            "--env.task=ur5e-lift",
            "--env.image_size=64",
            "--env.episode_length=10",
            "--env.prompt_repo_id=test/rs_tiny_prompts",
            "--env.prompt_max_frames=4",
            "--eval.n_episodes=1",
            "--eval.batch_size=1",
            "--policy.device=cpu",
            f"--output_dir={tmp_path / 'eval'}",
        ],
    ]
    commands.append(
        [
            "jept-eval-suite",
            f"--policy.path={tmp_path / 'train/checkpoints/last/pretrained_model'}",
            "--dataset.repo_id=test/rs_tiny_mix",
            "--n_episodes=1",
            "--batch_size=1",
            f"--output_dir={tmp_path / 'suite'}",
        ]
    )
    if policy_type != "jept":
        commands = commands[:1]
    for cmd in commands:
        proc = subprocess.run([str(bin_dir / cmd[0]), *cmd[1:]], capture_output=True, text=True, cwd=tmp_path)
        assert proc.returncode == 0, proc.stderr[-4000:]
    model = tmp_path / "train/checkpoints/last/pretrained_model"
    saved_type = policy_type if policy_type == "jept" else f"jept_{policy_type}"  # the config files' type
    assert json.loads((model / "config.json").read_text())["type"] == saved_type
    if policy_type != "jept":
        return
    info = json.loads((tmp_path / "eval/eval_info.json").read_text())
    assert info["overall"]["n_episodes"] == 1 and 0 <= info["overall"]["pc_success"] <= 100
    results = json.loads((tmp_path / "suite/results.json").read_text())
    assert list(results["table"]) == ["T_demo", "T_vid", "ur5e-lift", "Seen average", "Unseen average"]
    assert (tmp_path / "suite/results.png").stat().st_size > 1000
