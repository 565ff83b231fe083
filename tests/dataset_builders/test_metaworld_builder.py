"""The Meta-World builder on the real simulator, at tiny sizes (64x64 images, a few episodes)."""

import dataclasses
import json
import os
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pandas as pd
import psutil
import pytest

from dataset_builders import core
from dataset_builders.core import BUILD_FILE, BuildError, build, rollout_expert
from dataset_builders.metaworld import MetaworldBuildConfig, MetaworldSimulator, main
from lerobot_jept.envs.metaworld import STATE_DIM, JeptMetaworldEnv, task_description
from lerobot_jept.policies.discretization import snap_to_bins
from tests.conftest import SIM, TINY, load


def actions_of(root: Path) -> np.ndarray:
    frames = pd.concat(pd.read_parquet(p) for p in sorted((root / "data").glob("*/*.parquet")))
    return np.stack(frames["action"].to_numpy())


def lerobot_home() -> Path:
    return Path(os.environ["HF_LEROBOT_HOME"])


def test_repo_schemas(tiny_build):
    cfg, _ = tiny_build
    expected_episodes = {"demo": 6, "video": 3, "prompts": 8, "probe": 4, "mix": 9}
    for role, n in expected_episodes.items():
        ds = load(f"test/mw_tiny_{role}")
        assert ds.meta.total_episodes == n
        assert ds.meta.fps == 40 and ds.meta.robot_type == "sawyer"
        assert ds.features["observation.image"]["dtype"] == "video"
        assert tuple(ds.features["observation.image"]["shape"]) == (64, 64, 3)
        assert tuple(ds.features["observation.state"]["shape"]) == (STATE_DIM,)
        assert ("action" in ds.features) == (role in ("demo", "probe", "mix"))
        item = ds[0]
        assert item["observation.image"].shape == (3, 64, 64)
        assert item["observation.state"].dtype.is_floating_point
        if role in ("demo", "probe", "mix"):
            assert tuple(ds.features["action"]["shape"]) == (4,)


def test_executed_actions_are_bin_centres(tiny_build):
    actions = actions_of(lerobot_home() / "test/mw_tiny_demo")
    centres = np.linspace(-1, 1, 7)
    assert np.abs(actions[..., None] - centres).min(-1).max() < 1e-6


def test_mix_marks_video_frames_unlabelled_and_stats_use_labelled_frames_only(tiny_build):
    mix_root = lerobot_home() / "test/mw_tiny_mix"
    frames = pd.concat(pd.read_parquet(p) for p in sorted((mix_root / "data").glob("*/*.parquet")))
    actions = np.stack(frames["action"].to_numpy())
    labelled = np.stack(frames["observation.action_labelled"].to_numpy()).reshape(-1)
    tasks = pd.read_parquet(mix_root / "meta/tasks.parquet")
    video_task_index = tasks.loc[task_description("drawer-close-v3"), "task_index"]
    is_video = (frames["task_index"] == video_task_index).to_numpy()
    assert is_video.any() and (~is_video).any()
    assert (labelled == (~is_video).astype(np.float32)).all()
    assert (actions[is_video] == 0).all() and np.isfinite(actions).all()  # the neutral action
    mix = load("test/mw_tiny_mix")
    assert mix[len(mix) - 1]["observation.action_labelled"].item() == 0.0
    assert mix[0]["observation.action_labelled"].item() == 1.0
    demo = load("test/mw_tiny_demo")  # demos carry the marker too, so LeRobot can merge them with a mix
    assert demo.meta.features["observation.action_labelled"]["shape"] == (1,)
    assert (np.asarray(demo.hf_dataset.with_format("numpy")["observation.action_labelled"]) == 1).all()

    stats = json.loads((mix_root / "meta/stats.json").read_text())["action"]
    labelled = actions[~is_video]
    np.testing.assert_allclose(stats["mean"], labelled.mean(0), atol=1e-5)
    np.testing.assert_allclose(stats["min"], labelled.min(0))
    np.testing.assert_allclose(stats["max"], labelled.max(0))
    assert stats["count"] == [len(labelled)]
    # Labelled frames of the mix are exactly the demo repo's frames.
    np.testing.assert_array_equal(labelled, actions_of(lerobot_home() / "test/mw_tiny_demo"))


def test_task_strings_and_split_metadata(tiny_build):
    cfg, _ = tiny_build
    for role in ("demo", "video", "prompts", "probe", "mix"):
        meta = json.loads((lerobot_home() / f"test/mw_tiny_{role}/meta" / BUILD_FILE).read_text())
        assert meta["split"] == {"demo": cfg.demo_tasks, "video": cfg.video_tasks, "unseen": cfg.unseen_tasks}
        assert meta["protocol"]["action_repeat"] == 2 and meta["protocol"]["max_episode_steps"] == 250
        assert meta["repos"]["probe"] == "test/mw_tiny_probe"
    all_tasks = [*cfg.demo_tasks, *cfg.video_tasks, *cfg.unseen_tasks]
    for role in ("prompts", "probe"):  # every task of every split
        assert set(load(f"test/mw_tiny_{role}").meta.tasks.index) == {task_description(t) for t in all_tasks}
    for task in all_tasks:
        assert JeptMetaworldEnv(task).task_description == task_description(task)
    assert set(load("test/mw_tiny_mix").meta.tasks.index) == {
        task_description(t) for t in [*cfg.demo_tasks, *cfg.video_tasks]
    }


def test_prompt_seeds_are_disjoint_from_training_seeds(tiny_build):
    shards = lerobot_home() / "test/mw_tiny.build/shards"
    seeds = {
        role: {s for p in (shards / role).glob("*/*/shard.json") for s in json.loads(p.read_text())["seeds"]}
        for role in ("demo", "video", "prompts", "probe")
    }
    assert seeds["prompts"].isdisjoint(seeds["demo"] | seeds["video"])
    assert seeds["probe"].isdisjoint(seeds["demo"] | seeds["video"] | seeds["prompts"])
    assert len(list((shards / "probe").glob("*/*/shard.json"))) == 4  # one episode of each task


def test_first_frame_matches_env_reset_upright_and_not_blank(tiny_build):
    ds = load("test/mw_tiny_demo")
    shard = json.loads(
        (lerobot_home() / "test/mw_tiny.build/shards/demo/button-press-v3/0000/shard.json").read_text()
    )
    frame = (ds[0]["observation.image"].permute(1, 2, 0).numpy() * 255).astype(np.float32)
    env = JeptMetaworldEnv("button-press-v3", image_size=64)
    obs, _ = env.reset(seed=shard["seeds"][0])
    env.close()
    reference = obs["pixels"].astype(np.float32)
    assert frame.std() > 10  # not blank
    err = np.abs(frame - reference).mean()
    err_flipped = np.abs(frame - np.flip(reference, (0, 1))).mean()
    assert err < 15 and err_flipped > 3 * err  # lossy video at 64x64 vs an exact render
    np.testing.assert_allclose(ds[0]["observation.state"].numpy(), obs["agent_pos"], rtol=1e-5)


def test_rerun_is_a_no_op_that_keeps_everything(tiny_build):
    cfg, _ = tiny_build
    before = actions_of(lerobot_home() / "test/mw_tiny_mix")
    mtime = (lerobot_home() / "test/mw_tiny_demo/meta/info.json").stat().st_mtime
    build(cfg, SIM)
    np.testing.assert_array_equal(actions_of(lerobot_home() / "test/mw_tiny_mix"), before)
    assert (lerobot_home() / "test/mw_tiny_demo/meta/info.json").stat().st_mtime == mtime


def test_same_flags_give_same_episodes_with_any_worker_count(tmp_path):
    flags = dict(
        demo_tasks=["reach-v3"],
        video_tasks=[],
        unseen_tasks=[],
        episodes_per_task=3,
        prompts_per_task=1,
        probe_episodes_per_task=0,
        image_size=48,
        episodes_per_shard=1,
        seed=7,
    )
    build(MetaworldBuildConfig(repo_id="test/rep", root=str(tmp_path / "a"), num_workers=1, **flags), SIM)
    build(MetaworldBuildConfig(repo_id="test/rep", root=str(tmp_path / "b"), num_workers=2, **flags), SIM)
    for role in ("demo", "mix"):
        a, b = actions_of(tmp_path / f"a/test/rep_{role}"), actions_of(tmp_path / f"b/test/rep_{role}")
        np.testing.assert_array_equal(a, b)


def test_build_with_video_tasks_only_writes_the_repos_it_can(tmp_path, capsys):
    flags = dict(demo_tasks=[], video_tasks=["reach-v3"], unseen_tasks=[], episodes_per_task=1)
    flags.update(prompts_per_task=1, probe_episodes_per_task=0, image_size=48, num_workers=1)
    summary = build(MetaworldBuildConfig(repo_id="test/vonly", root=str(tmp_path), **flags), SIM)
    assert set(summary["repos"]) == {"video", "prompts"}
    assert (tmp_path / "test/vonly_video/meta/info.json").is_file() and not (
        tmp_path / "test/vonly_mix"
    ).exists()
    assert "jept-mix" in capsys.readouterr().out


@pytest.mark.parametrize(
    "flags, message",
    [
        ({"demo_tasks": ["button-pres-v3"]}, "Did you mean button-press-v3"),
        ({"demo_tasks": ["reach-v3"], "video_tasks": ["reach-v3"]}, "in both demo_tasks and video_tasks"),
        ({"episodes_per_task": 0}, "--episodes_per_task must be at least 1"),
        ({"demo_tasks": [], "video_tasks": []}, "Nothing to train on"),
        ({"repo_id": "no_org"}, "ORG/NAME"),
        ({"expert_random_prob": 1.0}, "--expert_random_prob must be in \\[0, 1\\)"),
    ],
)
def test_bad_flags_get_one_line_errors(tmp_path, flags, message):
    cfg = MetaworldBuildConfig(**{"repo_id": "test/bad", "root": str(tmp_path), **TINY, **flags})
    with pytest.raises(BuildError, match=message) as err:
        build(cfg, SIM)
    assert "\n" not in str(err.value)
    assert not any(tmp_path.iterdir())  # nothing written


def test_existing_repo_with_different_flags_is_refused(tiny_build, capsys):
    cfg, _ = tiny_build
    with pytest.raises(SystemExit, match="built with different flags: --episodes_per_task=3 \\(now 4\\)"):
        main(
            [
                "--repo_id=test/mw_tiny",
                "--episodes_per_task=4",
                "--image_size=64",
                "--prompts_per_task=2",
                "--probe_episodes_per_task=1",
                "--episodes_per_shard=2",
                "--demo_tasks=[button-press-v3, reach-v3]",
                "--video_tasks=[drawer-close-v3]",
                "--unseen_tasks=[handle-press-v3]",
            ]
        )


def test_build_recorded_before_the_probe_flag_resumes(tiny_build):
    """A build recorded by a version without --probe_episodes_per_task takes today's value instead of being
    refused for a changed flag."""
    cfg, _ = tiny_build
    record_path = lerobot_home() / "test/mw_tiny.build" / BUILD_FILE
    record = json.loads(record_path.read_text())
    del record["flags"]["probe_episodes_per_task"]
    record_path.write_text(json.dumps(record))
    build(cfg, SIM)
    assert json.loads(record_path.read_text())["flags"]["probe_episodes_per_task"] == 1


def test_build_recorded_before_the_random_action_flag_counts_as_zero(tiny_build):
    """A build recorded before --expert_random_prob existed was made without random actions: it resumes with
    0 and is refused with another value."""
    cfg, _ = tiny_build
    record_path = lerobot_home() / "test/mw_tiny.build" / BUILD_FILE
    record = json.loads(record_path.read_text())
    del record["flags"]["expert_random_prob"]
    record_path.write_text(json.dumps(record))
    with pytest.raises(BuildError, match="--expert_random_prob=0.0 \\(now 0.25\\)"):
        build(dataclasses.replace(cfg, expert_random_prob=0.25), SIM)
    build(cfg, SIM)
    assert json.loads(record_path.read_text())["flags"]["expert_random_prob"] == 0.0


def test_video_episodes_per_task_sets_the_videos_per_video_only_task(tiny_build):
    """--video_episodes_per_task records that many videos per video-only task and leaves the demos at
    --episodes_per_task; a build recorded before the flag had as many of each, so it resumes without it and is
    refused with it."""
    from dataset_builders.plan import plan_shards

    cfg, _ = tiny_build
    more = dataclasses.replace(cfg, video_episodes_per_task=5)
    count = {}
    for shard in plan_shards(more):
        count[shard.role, shard.task] = count.get((shard.role, shard.task), 0) + shard.num_episodes
    assert count["video", "drawer-close-v3"] == 5 and count["demo", "reach-v3"] == cfg.episodes_per_task
    assert sum(s.num_episodes for s in plan_shards(cfg) if s.role == "video") == cfg.episodes_per_task
    with pytest.raises(BuildError, match="--video_episodes_per_task must be at least 1"):
        build(dataclasses.replace(cfg, video_episodes_per_task=0), SIM)

    record_path = lerobot_home() / "test/mw_tiny.build" / BUILD_FILE
    record = json.loads(record_path.read_text())
    record["flags"].pop("video_episodes_per_task", None)
    record_path.write_text(json.dumps(record))
    with pytest.raises(BuildError, match="--video_episodes_per_task=None \\(now 5\\)"):
        build(more, SIM)
    build(cfg, SIM)
    assert json.loads(record_path.read_text())["flags"]["video_episodes_per_task"] is None


@pytest.mark.parametrize("random_prob", [0.0, 0.3])
def test_expert_random_prob_replaces_that_share_of_expert_actions(random_prob):
    """With --expert_random_prob=p about a share p of the steps record a random bin action instead of the
    expert's (snapped) action, the same ones for the same seed."""
    env = JeptMetaworldEnv("reach-v3", image_size=32, max_episode_steps=120)
    expert = env.expert_action
    runs = []
    for _ in range(2):
        asked = []
        env.expert_action = lambda asked=asked: asked.append(snap_to_bins(expert(), 7)) or expert()
        frames, _ = rollout_expert(env, 5, 7, random_prob)
        recorded = np.stack([f["action"] for f in frames])
        runs.append((recorded, (recorded != np.stack(asked)).any(-1).mean()))
    env.close()
    np.testing.assert_array_equal(runs[0][0], runs[1][0])
    centres = np.linspace(-1, 1, 7)
    assert np.abs(runs[0][0][..., None] - centres).min(-1).max() < 1e-6
    replaced = runs[0][1]
    assert replaced == 0 if random_prob == 0 else 0.15 < replaced < 0.45, replaced


def test_foreign_repo_is_not_overwritten(tmp_path):
    (tmp_path / "test/foreign_demo").mkdir(parents=True)
    cfg = MetaworldBuildConfig(repo_id="test/foreign", root=str(tmp_path), **TINY)
    with pytest.raises(BuildError, match="were not built by this builder"):
        build(cfg, SIM)


class BrokenSimulator(MetaworldSimulator):
    """Its env cannot be made: the error happens in the builder's rollout process."""

    def make_env(self, task, cfg, role="demo"):
        raise RuntimeError(f"no env for {task} here")


def test_rollout_process_errors_reach_the_caller(tmp_path):
    cfg = MetaworldBuildConfig(repo_id="test/broken", root=str(tmp_path), **TINY)
    with pytest.raises(RuntimeError, match="no env for [a-z-]+v3 here"):
        build(cfg, BrokenSimulator())
    assert not core._RENDERER  # the rollout process is stopped with the failed build
    assert not (tmp_path / "test/broken_demo").exists()


def test_missing_renderer_names_the_fix(tmp_path, monkeypatch):
    import ctypes.util

    from lerobot_jept.envs.rendering import RendererUnavailableError, setup_offscreen_gl

    monkeypatch.setenv("MUJOCO_GL", "egl")
    monkeypatch.setattr(ctypes.util, "find_library", lambda name: None)
    with pytest.raises(RendererUnavailableError, match="apt-get install libegl1 .*MUJOCO_GL=osmesa"):
        setup_offscreen_gl()
    monkeypatch.setenv("MUJOCO_GL", "opengl-please")
    with pytest.raises(RendererUnavailableError, match="set MUJOCO_GL to one of"):
        setup_offscreen_gl()


@pytest.mark.slow
def test_killed_build_resumes_without_loss_or_duplicates(tmp_path):
    """Kill the CLI mid-build (SIGKILL) with two worker processes, check that they die with it and the repos,
    re-run, check the result equals a clean build."""
    flags = [
        "--repo_id=test/kill",
        "--demo_tasks=[button-press-v3, reach-v3]",
        "--video_tasks=[drawer-close-v3]",
        "--unseen_tasks=[]",
        "--episodes_per_task=4",
        "--prompts_per_task=1",
        "--probe_episodes_per_task=0",
        "--image_size=48",
        "--episodes_per_shard=1",
        "--num_workers=2",
    ]

    def args_for(root):
        return [f"--root={root}", *flags]

    cmd = [
        sys.executable,
        "-c",
        "from dataset_builders.metaworld import main; main()",
        *args_for(tmp_path / "killed"),
    ]
    proc = subprocess.Popen(cmd, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    shards = tmp_path / "killed/test/kill.build/shards/demo"
    deadline = time.time() + 300
    while time.time() < deadline and len(list(shards.glob("*/*/shard.json"))) < 3:
        time.sleep(0.2)
    children = psutil.Process(proc.pid).children(recursive=True)
    assert len(children) >= 2
    os.kill(proc.pid, signal.SIGKILL)
    proc.wait()
    _, alive = psutil.wait_procs(children, timeout=30)
    assert not alive, "a worker outlived the killed build (it would write the shards the re-run records)"
    done_before = len(list(shards.glob("*/*/shard.json")))
    assert 3 <= done_before < 8, "the kill must land mid-build"

    main(args_for(tmp_path / "killed"))  # resume
    main(args_for(tmp_path / "clean"))  # reference: one uninterrupted build
    for role in ("demo", "mix"):
        resumed = actions_of(tmp_path / f"killed/test/kill_{role}")
        clean = actions_of(tmp_path / f"clean/test/kill_{role}")
        np.testing.assert_array_equal(resumed, clean)
    from lerobot.datasets.lerobot_dataset import LeRobotDataset

    for role, n in {"demo": 8, "video": 4, "prompts": 3, "mix": 12}.items():
        ds = LeRobotDataset(f"test/kill_{role}", root=tmp_path / f"killed/test/kill_{role}")
        assert ds.meta.total_episodes == n
        episode_index = ds.hf_dataset["episode_index"]
        assert sorted(set(int(e) for e in episode_index)) == list(range(n))
    assert not list((tmp_path / "killed").rglob("*.tmp"))
    shutil.rmtree(tmp_path)


@pytest.mark.parametrize("role", ["demo", "video"])
def test_lerobot_dataset_viz_saves_a_recording(tiny_build, tmp_path, role):
    """LeRobot's own viewer reads the repos, with and without an `action` feature."""
    proc = subprocess.run(
        [
            str(Path(sys.executable).parent / "lerobot-dataset-viz"),
            f"--repo-id=test/mw_tiny_{role}",
            "--episode-index=0",
            "--save=1",
            f"--output-dir={tmp_path}",
            "--num-workers=0",
        ],
        capture_output=True,
        text=True,
    )
    assert proc.returncode == 0, proc.stderr[-3000:]
    recordings = list(tmp_path.glob("*.rrd"))
    assert len(recordings) == 1 and recordings[0].stat().st_size > 10_000
