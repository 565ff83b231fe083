"""Your own data: ``jept-mix`` from any LeRobotDatasets, ``jept-prompts`` from plain video files, and mixes that
LeRobot's own dataset tools (``lerobot-edit-dataset``) keep whole."""

import json
import shutil

import numpy as np
import pytest
import torch

from lerobot_jept.datasets.mixing import MixConfig, MixError, run_mix
from lerobot_jept.datasets.prompt_videos import PromptVideosConfig, PromptVideosError, make_prompt_bank
from lerobot_jept.envs.metaworld import task_description
from tests.conftest import load
from tests.lerobot_jept.test_end_to_end import CONFIG, MIX, TINY_TRAIN, lerobot_eval, run

MARKER = "observation.action_labelled"
DEMO_TASKS = {task_description(t) for t in ("button-press-v3", "reach-v3")}


def write_repo(
    repo_id: str, frames: list[list[dict]], tasks: list[str], fps: int, robot_type: str, size: int, state: int
):
    """A LeRobotDataset written through LeRobot's own API (camera + state, no action), one episode per list."""
    from lerobot.datasets.lerobot_dataset import LeRobotDataset

    features = {
        "observation.image": {
            "dtype": "video",
            "shape": (size, size, 3),
            "names": ["height", "width", "channels"],
        },
        "observation.state": {"dtype": "float32", "shape": (state,), "names": None},
    }
    ds = LeRobotDataset.create(
        repo_id=repo_id, fps=fps, features=features, robot_type=robot_type, use_videos=True
    )
    for episode, task in zip(frames, tasks, strict=True):
        for frame in episode:
            ds.add_frame({**frame, "task": task})
        ds.save_episode()
    ds.finalize()


@pytest.fixture(scope="module")
def foreign_video(tiny_build):
    """Action-free episodes from "another source": the tiny build's video frames re-written by LeRobot's API
    with another robot type."""
    source = load("test/mw_tiny_video")
    episodes, tasks = [], []
    for ep in range(source.meta.total_episodes):
        info = source.meta.episodes[ep]
        rows = [source[i] for i in range(info["dataset_from_index"], info["dataset_to_index"])]
        episodes.append(
            [
                {
                    "observation.image": (r["observation.image"].permute(1, 2, 0).numpy() * 255)
                    .round()
                    .astype(np.uint8),
                    "observation.state": r["observation.state"].numpy(),
                }
                for r in rows
            ]
        )
        tasks.append(rows[0]["task"])
    write_repo("test/foreign_video", episodes, tasks, source.meta.fps, "phone", 64, 18)
    return "test/foreign_video"


def labelled_frames(ds) -> np.ndarray:
    """(frames,) bool: the frames a mix marks as labelled."""
    return np.asarray(ds.hf_dataset.with_format("numpy")[MARKER]).reshape(-1) == 1


def labels_by_episode(ds) -> dict[int, np.ndarray]:
    table = ds.hf_dataset.with_format("numpy")
    marker = np.asarray(table[MARKER]).reshape(-1) if MARKER in ds.meta.features else None
    episodes = np.asarray(table["episode_index"]).reshape(-1)
    return {int(e): (marker[episodes == e] if marker is not None else None) for e in np.unique(episodes)}


def assert_whole(repo_id: str) -> None:
    """Every frame loads, and an episode is labelled (all frames) exactly when its task is a demo task."""
    ds = load(repo_id)
    for i in range(len(ds)):
        frame = ds[i]
        assert torch.isfinite(frame["action"]).all() if "action" in frame else True
    table = ds.hf_dataset.with_format("numpy")
    tasks = np.asarray(table["task_index"]).reshape(-1)
    episodes = np.asarray(table["episode_index"]).reshape(-1)
    for ep, marker in labels_by_episode(ds).items():
        task = ds.meta.tasks.index[tasks[episodes == ep][0]]
        expected = 1.0 if task in DEMO_TASKS else 0.0
        assert marker is None and expected == 1.0 or (marker == expected).all(), (repo_id, ep, task)
    stats = ds.meta.stats["action"]
    assert all(np.isfinite(np.asarray(v)).all() for v in stats.values())


@pytest.mark.slow
def test_lerobot_edit_dataset_keeps_mixes_whole(tiny_build, tmp_path):
    """delete_episodes, split, merge, remove_feature and recompute_stats on the builder's repos."""
    from lerobot.utils.constants import HF_LEROBOT_HOME

    edit = ["lerobot-edit-dataset"]
    n = load(MIX).meta.total_episodes
    run(
        [
            *edit,
            f"--repo_id={MIX}",
            "--new_repo_id=test/ed_deleted",
            "--operation.type=delete_episodes",
            "--operation.episode_indices=[0, 5]",
        ],
        tmp_path,
    )
    assert load("test/ed_deleted").meta.total_episodes == n - 2
    assert_whole("test/ed_deleted")
    shutil.copytree(HF_LEROBOT_HOME / MIX, HF_LEROBOT_HOME / "test/ed_split")
    run(
        [
            *edit,
            "--repo_id=test/ed_split",
            "--operation.type=split",
            "--operation.splits={train: 0.5, val: 0.5}",
        ],
        tmp_path,
    )
    for name in ("train", "val"):
        assert_whole(f"test/ed_split_{name}")
    run(
        [
            *edit,
            "--new_repo_id=test/ed_merged",
            "--operation.type=merge",
            "--operation.repo_ids=[test/mw_tiny_demo, test/mw_tiny_mix]",
        ],
        tmp_path,
    )
    merged = load("test/ed_merged")
    assert merged.meta.total_episodes == n + load("test/mw_tiny_demo").meta.total_episodes
    assert_whole("test/ed_merged")
    shutil.copytree(HF_LEROBOT_HOME / MIX, HF_LEROBOT_HOME / "test/ed_stats")
    run([*edit, "--repo_id=test/ed_stats", "--operation.type=recompute_stats"], tmp_path)
    assert_whole("test/ed_stats")
    run(
        [
            *edit,
            "--repo_id=test/mw_tiny_demo",
            "--new_repo_id=test/ed_plain_demo",
            "--operation.type=remove_feature",
            f"--operation.feature_names=[{MARKER}]",
        ],
        tmp_path,
    )
    assert MARKER not in load("test/ed_plain_demo").meta.features
    assert_whole("test/ed_plain_demo")  # no marker: every frame labelled by its finite action


def test_jept_mix_names_every_difference_and_the_fix(tiny_build):
    frames = [
        [{"observation.image": np.zeros((32, 32, 3), np.uint8), "observation.state": np.zeros(8, np.float32)}]
        * 3
    ]
    write_repo("test/odd_video", frames, ["something"], 30, "other", 32, 8)
    with pytest.raises(MixError) as err:
        run_mix(
            MixConfig(
                demo_repo_ids=["test/mw_tiny_demo"],
                video_repo_ids=["test/odd_video"],
                output_repo_id="test/no",
            )
        )
    text = str(err.value)
    assert (
        "30 fps" in text
        and "(32, 32, 3)" in text
        and "(64, 64, 3)" in text
        and "(8,)" in text
        and "(18,)" in text
    )
    with pytest.raises(MixError, match="--ignore_video_actions=true"):
        run_mix(
            MixConfig(
                demo_repo_ids=["test/mw_tiny_demo"],
                video_repo_ids=["test/mw_tiny_demo"],
                output_repo_id="test/no",
            )
        )


def test_jept_mix_weights_a_repo_listed_twice(tiny_build):
    """A repo listed twice enters the mix twice: the way to keep the labelled share of each batch when videos
    outnumber the demos (LeRobot's training samples frames uniformly)."""
    demo, video = load("test/mw_tiny_demo"), load("test/mw_tiny_video")
    run_mix(
        MixConfig(
            demo_repo_ids=["test/mw_tiny_demo", "test/mw_tiny_demo"],
            video_repo_ids=["test/mw_tiny_video"],
            output_repo_id="test/twice_mix",
        )
    )
    mix = load("test/twice_mix")
    assert mix.meta.total_episodes == 2 * demo.meta.total_episodes + video.meta.total_episodes
    labelled = labelled_frames(mix)
    assert labelled.sum() == 2 * demo.meta.total_frames
    copy = mix.meta.episodes[demo.meta.total_episodes]["dataset_from_index"]
    first, again = mix[0], mix[copy]
    assert torch.equal(first["observation.state"], again["observation.state"])
    assert torch.equal(first["action"], again["action"])
    assert_whole("test/twice_mix")


def write_mp4(path, size: tuple[int, int], frames: int, vfr: bool = False) -> None:
    import fractions

    import av

    with av.open(str(path), "w") as container:
        stream = container.add_stream("libx264", rate=30)
        stream.width, stream.height = size
        stream.pix_fmt = "yuv444p" if size[0] % 2 else "yuv420p"
        stream.time_base = fractions.Fraction(1, 30)
        stream.codec_context.max_b_frames = 0
        pts = 0
        for i in range(frames):
            image = np.zeros((size[1], size[0], 3), np.uint8)
            image[..., 0] = 40 + 200 * i // frames
            frame = av.VideoFrame.from_ndarray(image, format="rgb24")
            frame.pts, frame.time_base = pts, stream.time_base
            pts += (1 if i % 2 else 3) if vfr else 1
            for packet in stream.encode(frame):
                container.mux(packet)
        for packet in stream.encode():
            container.mux(packet)


def test_jept_prompts_from_plain_videos(tmp_path):
    from lerobot_jept.policies.prompts import PromptBank

    (tmp_path / "close").mkdir()
    (tmp_path / "open").mkdir()
    write_mp4(tmp_path / "close/a.mp4", (101, 75), 40, vfr=True)  # odd size, variable frame rate
    write_mp4(tmp_path / "close/b.mp4", (64, 64), 20)
    write_mp4(tmp_path / "open/c.mov", (80, 120), 30)
    make_prompt_bank(
        PromptVideosConfig(videos=str(tmp_path), output_repo_id="test/own_prompts", fps=10, image_size=32)
    )
    bank = PromptBank("test/own_prompts", None, 100, 32)
    assert bank.tasks == ["close", "open"] and bank.episodes("close") == [0, 1]
    # a.mp4: frames at 0, 0.1, 0.133, 0.233, ... (40 frames over 2.6 s) -> 10 fps ticks 0 .. 2.6 s
    assert len(bank.video(0)) == 27 and bank.video(0).shape[1:] == (3, 32, 32)
    assert len(bank.video(1)) == 7  # 20 frames at 30 fps: 0.633 s -> ticks 0, 0.1, ..., 0.6
    brightness = bank.video(0).float()[:, 0].mean((1, 2))
    assert (brightness.diff() >= 0).all() and brightness[-1] > brightness[0] + 100  # in time order
    corrupt = tmp_path / "corrupt.mp4"
    corrupt.write_bytes(b"\x00\x00\x00\x18ftypmp42" + b"garbage" * 100)
    before = sorted(p.name for p in bank.dataset.root.rglob("*"))
    with pytest.raises(PromptVideosError, match="corrupt.mp4 cannot be decoded"):
        make_prompt_bank(
            PromptVideosConfig(
                videos=str(corrupt), task="x", output_repo_id="test/own_prompts", fps=10, image_size=32
            )
        )
    assert sorted(p.name for p in bank.dataset.root.rglob("*")) == before  # nothing written
    make_prompt_bank(
        PromptVideosConfig(
            videos=str(tmp_path / "open/*.mov"),
            task="push",
            output_repo_id="test/own_prompts",
            fps=10,
            image_size=32,
        )
    )
    assert PromptBank("test/own_prompts", None, 100, 32).tasks == [
        "close",
        "open",
        "push",
    ]  # added to the bank


@pytest.mark.slow
def test_own_data_the_whole_way(foreign_video, tmp_path):
    """A builder's demos + action-free episodes written through LeRobot's API -> jept-mix -> lerobot-train ->
    jept-prompts from mp4 files -> lerobot-eval prompted by that bank."""
    log = run(
        [
            "jept-mix",
            "--demo_repo_ids=[test/mw_tiny_demo]",
            f"--video_repo_ids=[{foreign_video}]",
            "--output_repo_id=test/own_mix",
        ],
        tmp_path,
    )
    assert "Wrote test/own_mix" in log
    mix = load("test/own_mix")
    build = json.loads((mix.root / "meta/jept_build.json").read_text())
    assert build["split"] == {
        "demo": ["button-press-v3", "reach-v3"],
        "video": ["drawer-close-v3"],
        "unseen": [],
    }
    assert build["sources"]["video"] == [{"repo_id": foreign_video, "robot_type": "phone"}]
    assert_whole("test/own_mix")
    demo = load("test/mw_tiny_demo")
    labelled = labelled_frames(mix)
    assert labelled.sum() == demo.meta.total_frames
    actions = np.stack(mix.hf_dataset.with_format("numpy")["action"])
    np.testing.assert_allclose(mix.meta.stats["action"]["mean"], actions[labelled].mean(0), atol=1e-5)
    again = run(
        ["jept-mix", "--demo_repo_ids=[test/mw_tiny_demo]", "--output_repo_id=test/own_mix"],
        tmp_path,
        ok=False,
    )
    assert "already exists" in again

    out = tmp_path / "train"
    run(
        [
            "lerobot-train",
            f"--config_path={CONFIG}",
            "--dataset.repo_id=test/own_mix",
            "--policy.prompt_repo_id=test/mw_tiny_prompts",
            "--steps=2",
            "--save_freq=2",
            f"--output_dir={out}",
            *TINY_TRAIN,
        ],
        tmp_path,
    )
    videos = tmp_path / "my_videos"
    videos.mkdir()
    write_mp4(videos / "press.mp4", (120, 90), 30)
    run(
        [
            "jept-prompts",
            f"--videos={videos}",
            f"--task={task_description('handle-press-v3')}",
            "--output_repo_id=test/own_handle_prompts",
            "--image_size=64",
            "--fps=10",
        ],
        tmp_path,
    )
    model = out / "checkpoints/last/pretrained_model"
    info = lerobot_eval(model, tmp_path / "eval", tmp_path, prompts="test/own_handle_prompts")
    assert info["overall"]["n_episodes"] == 1
