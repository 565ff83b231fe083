"""Play episodes (``--play_episodes_per_task``) and the inverse-dynamics screen (``jept-screen``) on a real
tiny Meta-World build: one demo task, its scene-mate as the video-only task, play in both scenes."""

import json

import numpy as np
import pytest

from dataset_builders.core import build
from dataset_builders.metaworld import MetaworldBuildConfig
from lerobot_jept.datasets.mixing import labelled_mask
from lerobot_jept.envs.metaworld import STATE_DIM
from lerobot_jept.evaluation.screen import ScreenConfig, load_frames, main, markdown, screen
from tests.conftest import SIM, load

PLAY = dict(
    demo_tasks=["window-open-v3"],
    video_tasks=["window-close-v3"],
    unseen_tasks=[],
    episodes_per_task=2,
    prompts_per_task=1,
    probe_episodes_per_task=1,
    play_episodes_per_task=2,
    image_size=32,
    max_episode_steps=60,
    num_workers=1,
)


@pytest.fixture(scope="module")
def play_build():
    summary = build(MetaworldBuildConfig(repo_id="test/play", **PLAY), SIM)
    return summary


def test_play_episodes_are_labelled_random_motion_in_each_scene_and_join_the_mix(play_build):
    assert set(play_build["repos"]) == {"demo", "video", "play", "prompts", "probe", "mix"}
    play = load("test/play_play")
    build_meta = json.loads((play.root / "meta/jept_build.json").read_text())
    assert build_meta["play_tasks"] == ["play:window-open-v3", "play:window-close-v3"]
    assert "play:window-close-v3" not in sum(build_meta["split"].values(), [])  # in no split
    strings = {build_meta["task_descriptions"][t] for t in build_meta["play_tasks"]}
    assert set(play.meta.tasks.index) == strings and play.meta.total_episodes == 4
    # every play episode is kept and runs to the episode limit; its actions are bin centres, held for a while
    # (so the arm travels) and varied (not an expert's)
    table = play.hf_dataset.with_format("numpy")
    actions, episodes = np.stack(table["action"]), table["episode_index"]
    assert play.meta.total_frames == 4 * PLAY["max_episode_steps"]
    assert np.isin(np.round(actions * 3), np.arange(-3, 4)).all()  # 7 bins over [-1, 1]
    first = actions[episodes == episodes[0]]
    held = (first[1:] == first[:-1]).all(1).mean()
    assert 0.6 < held < 0.95 and len({tuple(a) for a in first}) > 3
    # the mix: demo + play labelled, video unlabelled; the prompt bank has the play tasks too
    mix = load("test/play_mix")
    assert mix.meta.total_episodes == 2 + 2 + 4
    assert labelled_mask(mix).sum() == load("test/play_demo").meta.total_frames + play.meta.total_frames
    assert strings <= set(load("test/play_prompts").meta.tasks.index)
    record = json.loads((mix.root.parent / "play.build/jept_build.json").read_text())
    assert record["metadata"]["flags"]["play_episodes_per_task"] == 2


def test_screen_scores_each_arm_per_task_and_over_the_video_only_tasks(play_build, tmp_path):
    cfg = ScreenConfig(
        probe_repo_id="test/play_probe",
        arms={"demos": ["test/play_demo"], "demos + play": ["test/play_demo", "test/play_play"]},
        seeds=[0, 1],
    )
    results = screen(cfg)
    demos, with_play = results["arms"]["demos"], results["arms"]["demos + play"]
    assert with_play["labelled_frames"] > demos["labelled_frames"]
    for arm in (demos, with_play):
        rows = arm["per_task"]
        assert {t: r["split"] for t, r in rows.items()} == {
            "window-open-v3": "demo",
            "window-close-v3": "video",
        }
        assert arm["video_only_mean"] == pytest.approx(rows["window-close-v3"]["whole_mean"])
        assert len(rows["window-close-v3"]["whole"]) == 2 and 0 <= arm["video_only_mean"] <= 1
    # play can only add labels: the share of the probe's actions in the labels' support does not fall
    assert (
        with_play["per_task"]["window-close-v3"]["in_support"]
        >= demos["per_task"]["window-close-v3"]["in_support"]
    )
    assert "| **video-only mean** | video |" in markdown(results)

    main(
        [
            "--probe_repo_id=test/play_probe",
            "--arms={demos: [test/play_demo]}",
            "--seeds=[0]",
            f"--output_dir={tmp_path}",
        ]
    )
    assert json.loads((tmp_path / "screen.json").read_text())["arms"]["demos"]["per_task"]
    assert (tmp_path / "screen.png").stat().st_size > 1000


def test_screen_refuses_unlabelled_repos_and_missing_arms(play_build, tmp_path):
    with pytest.raises(SystemExit, match="test/play_video has no `action` column"):
        main(["--probe_repo_id=test/play_probe", "--arms={v: [test/play_video]}", f"--output_dir={tmp_path}"])
    with pytest.raises(SystemExit, match="--arms="):
        main(["--probe_repo_id=test/play_probe"])
    frames = load_frames("test/play_play", None, steps=2, num_bins=7)
    assert frames["x"].shape[1] == 2 * STATE_DIM  # the next two self-state changes
    with_state = load_frames("test/play_play", None, steps=2, num_bins=7, with_state=True)
    assert with_state["x"].shape[1] == 3 * STATE_DIM  # s_t, then the two changes
    np.testing.assert_array_equal(with_state["x"][:, STATE_DIM:], frames["x"])
    # --history=1: the change into s_t first, then the next one; each episode loses its first frame
    one = load_frames("test/play_play", None, steps=1, num_bins=7)
    past = load_frames("test/play_play", None, steps=1, num_bins=7, history=1)
    episodes = len(one["x"]) - len(past["x"])
    assert episodes > 0 and past["x"].shape[1] == 2 * STATE_DIM
    np.testing.assert_array_equal(
        past["x"][1, :STATE_DIM], past["x"][0, STATE_DIM:]
    )  # same episode, t -> t+1
    np.testing.assert_array_equal(past["x"][:, STATE_DIM:][:5], one["x"][1:6])
    with pytest.raises(SystemExit, match="--history must be 0 or more"):
        main(["--probe_repo_id=test/play_probe", "--arms={p: [test/play_play]}", "--history=-1"])


def test_play_flag_is_checked():
    from dataset_builders.config import BuildError, validate
    from dataset_builders.robosuite import RobosuiteBuildConfig, RobosuiteSimulator

    with pytest.raises(BuildError, match="--play_episodes_per_task must be 0 or more"):
        build(MetaworldBuildConfig(repo_id="test/bad_play", **{**PLAY, "play_episodes_per_task": -1}), SIM)
    with pytest.raises(
        BuildError, match="--play_policy='wander' is not available for metaworld: use one of random"
    ):
        validate(MetaworldBuildConfig(repo_id="test/bad_play", **PLAY, play_policy="wander"), SIM)
    robosuite = RobosuiteBuildConfig(repo_id="test/bad_play", play_episodes_per_task=1, play_policy="reach")
    with pytest.raises(BuildError, match="'reach' is not available for robosuite: use one of random"):
        validate(robosuite, RobosuiteSimulator())


def test_reach_play_moves_the_scenes_object_both_ways_and_runs_to_the_episode_limit():
    """``--play_policy=reach`` in the drawer-close scene: the drawer is shut within a few reaches (the scene's
    task succeeds) and the episode goes on to its last step, as play has no task; the actions are bin centres,
    mostly the experts' saturated moves, with a gripper command held per reach."""
    from dataset_builders.record import rollout_play
    from lerobot_jept.envs.metaworld import JeptMetaworldEnv

    env = JeptMetaworldEnv("drawer-close-v3", image_size=32, max_episode_steps=80)
    try:
        env.reset(seed=0)
        start = env.hand_and_object()[1]
        frames, kept = rollout_play(env, seed=0, action_bins=7, steps=80, policy="reach")
        drawer = env.hand_and_object()[1]
        again, _ = rollout_play(env, seed=0, action_bins=7, steps=80, policy="reach")
    finally:
        env.close()
    assert kept and len(frames) == 80
    assert np.abs(drawer - start).max() > 0.1  # the drawer moved (shut) on the way
    actions = np.stack([f["action"] for f in frames])
    assert np.isin(np.round(actions * 3), np.arange(-3, 4)).all()
    assert set(np.unique(actions[:, 3])) <= {-1.0, 1.0} and len(set(actions[:, 3])) == 2
    assert (np.abs(actions[:, :3]) == 1).any(1).mean() > 0.5  # moves towards a point, at the experts' gain
    assert len({tuple(np.sign(a[:3])) for a in actions}) > 6  # in many directions around the object
    np.testing.assert_array_equal(actions, np.stack([f["action"] for f in again]))  # the seed fixes the play


def test_the_suite_prints_the_floor_beside_each_row():
    from lerobot_jept.evaluation.suite import markdown

    per_task = {"b": {"split": "video", "pc_success": 40.0, "n_episodes": 10}}
    table = markdown(
        {"T_vid": 40.0, "Unseen average": float("nan")}, per_task, False, "jept", {"T_vid": 20.0}
    )
    assert "| Task | jept (this run) | random 7-bin |" in table and "| T_vid | 40.0 | 20.0 |" in table
    assert "| Unseen average | nan | - |" in table


def test_scene_mates_are_the_builds_other_task_of_the_scene():
    from lerobot_jept.evaluation.suite import SuiteError, scene_mate_of

    build = {"split": {"demo": ["window-open-v3", "reach-v3"], "video": ["window-close-v3"], "unseen": []}}
    assert scene_mate_of(build, ["window-close-v3"]) == {"window-close-v3": "window-open-v3"}
    with pytest.raises(SuiteError, match="reach-v3 has no scene-mate"):
        scene_mate_of(build, ["reach-v3"])


@pytest.mark.slow
def test_jept_trains_on_a_mix_with_play_and_is_evaluated_under_the_scene_mates_prompt(play_build, tmp_path):
    """lerobot-train on the mix with play episodes (their prompts come from the bank like any task's), then
    the suite on the video-only task alone, with its own prompt and with its scene-mate's."""
    from tests.lerobot_jept.test_end_to_end import CONFIG, TINY_TRAIN, run

    model = tmp_path / "train/checkpoints/last/pretrained_model"
    run(
        [
            "lerobot-train",
            f"--config_path={CONFIG}",
            "--dataset.repo_id=test/play_mix",
            "--policy.prompt_repo_id=test/play_prompts",
            "--policy.image_size=32",
            "--steps=2",
            "--save_freq=2",
            f"--output_dir={tmp_path / 'train'}",
            *TINY_TRAIN,
        ],
        tmp_path,
    )
    run(
        [
            "jept-eval-suite",
            f"--policy.path={model}",
            "--dataset.repo_id=test/play_mix",
            "--splits=[video]",
            "--scene_mate_prompts=true",
            "--n_episodes=1",
            "--batch_size=1",
            "--episode_length=8",
            "--probe=false",
            "--floor_episodes=2",
            f"--output_dir={tmp_path / 'suite'}",
        ],
        tmp_path,
    )
    results = json.loads((tmp_path / "suite/results.json").read_text())
    assert results["recipe"] == "plus" and list(results["per_task"]) == ["window-close-v3"]
    mate = results["per_task"]["window-close-v3"]["scene_mate"]
    assert mate["prompt_task"] == "window-open-v3" and mate["n_episodes"] == 1
    assert "T_vid, scene-mate's prompt" in results["table"] and "T_demo" not in results["table"]
    assert (tmp_path / "suite/tasks/window-close-v3.prompt_window-open-v3/eval_info.json").is_file()
    floor = results["random_floor"]["window-close-v3"]
    assert len(floor["successes"]) == 2 and set(results["random_floor_table"]) >= {"T_vid"}
    assert "random 7-bin |" in (tmp_path / "suite/results.md").read_text()
