"""``jept-prompts``: plain video files (mp4, webm, mov, ...; any size and frame rate) -> a prompt bank, the
LeRobotDataset that ``--policy.prompt_repo_id``, ``--env.prompt_repo_id`` and ``jept-eval-suite`` take.

One episode per file, with the task given by ``--task`` (or, without it, the name of each file's sub-folder of
``--videos``). Frames are sampled at ``--fps`` by their timestamps (variable frame rates are fine), centre-cropped
to a square and resized to ``--image_size``. Every file is decoded before anything is written, so a corrupt file
stops the command with its name and nothing changes; a second call with the same ``--output_repo_id`` adds its
episodes (and tasks) to the bank.

    jept-prompts --videos=my_videos/ --task="close the drawer" --output_repo_id=ORG/NAME_prompts --image_size=96
"""

import glob
import logging
import shutil
import sys
from dataclasses import dataclass
from pathlib import Path

import draccus
import numpy as np
import torch
from tqdm import tqdm

from lerobot_jept.datasets.mixing import push_dataset
from lerobot_jept.policies.prompts import resize_frames

VIDEO_SUFFIXES = (".mp4", ".webm", ".mov", ".mkv", ".avi", ".m4v")
CAMERA_KEY = "observation.image"


@dataclass
class PromptVideosConfig:
    videos: str = ""  # a folder (one task per sub-folder unless --task) or a glob of video files
    task: str | None = None  # the task string of every video; must equal the env's task description
    output_repo_id: str = ""
    root: str | None = None  # default: $HF_LEROBOT_HOME/<output_repo_id>
    fps: int = 10
    image_size: int = 224  # the policy's resolution (--policy.image_size)
    push_to_hub: bool = False
    private: bool = False


class PromptVideosError(ValueError):
    pass


def find_videos(cfg: PromptVideosConfig) -> list[tuple[Path, str]]:
    """(file, task) pairs, sorted."""
    source = Path(cfg.videos)
    if source.is_dir():
        files = sorted(p for p in source.rglob("*") if p.suffix.lower() in VIDEO_SUFFIXES)
    else:
        files = sorted(Path(p) for p in glob.glob(cfg.videos, recursive=True))
    if not files:
        raise PromptVideosError(
            f"No video files ({', '.join(VIDEO_SUFFIXES)}) found at --videos={cfg.videos}: give a folder or a glob."
        )
    if cfg.task:
        return [(f, cfg.task) for f in files]
    if not source.is_dir() or any(f.parent == source for f in files):
        raise PromptVideosError(
            "Without --task, the task of each video is the name of its sub-folder of --videos, but "
            f'{cfg.videos} has videos outside sub-folders: pass --task="..." (the env\'s task description).'
        )
    return [(f, f.relative_to(source).parts[0]) for f in files]


def read_video(path: Path, fps: int, size: int) -> np.ndarray:
    """(T, size, size, 3) uint8 frames sampled every 1/fps seconds (the latest frame at or before each tick)."""
    import av

    try:
        with av.open(str(path)) as container:
            stream = container.streams.video[0]
            frames, times = [], []
            for frame in container.decode(stream):
                frames.append(frame.to_ndarray(format="rgb24"))
                times.append(float(frame.time) if frame.time is not None else len(times) / fps)
    except (av.error.FFmpegError, IndexError, ValueError) as err:
        raise PromptVideosError(
            f"{path} cannot be decoded ({type(err).__name__}: {err}); nothing was written."
        ) from err
    if not frames:
        raise PromptVideosError(f"{path} has no video frames; nothing was written.")
    times = np.asarray(times) - times[0]
    ticks = np.arange(0.0, times[-1] + 1e-9, 1.0 / fps)
    picked = np.clip(np.searchsorted(times, ticks + 1e-6, side="right") - 1, 0, len(frames) - 1)
    video = torch.from_numpy(np.stack([frames[i] for i in picked])).permute(0, 3, 1, 2)  # (T, 3, H, W)
    h, w = video.shape[-2:]
    side = min(h, w)
    top, left = (h - side) // 2, (w - side) // 2
    video = video[..., top : top + side, left : left + side].float() / 255
    out = resize_frames(video, size)
    return (out * 255).round().clamp(0, 255).to(torch.uint8).permute(0, 2, 3, 1).numpy()


def write_bank(cfg: PromptVideosConfig, videos: list[tuple[np.ndarray, str]], root: Path) -> None:
    from lerobot.datasets.lerobot_dataset import LeRobotDataset

    features = {
        CAMERA_KEY: {
            "dtype": "video",
            "shape": (cfg.image_size, cfg.image_size, 3),
            "names": ["height", "width", "channels"],
        }
    }
    dataset = LeRobotDataset.create(
        repo_id=cfg.output_repo_id, fps=cfg.fps, features=features, root=root, use_videos=True
    )
    for frames, task in tqdm(videos, desc="writing prompts", unit="video"):
        for frame in frames:
            dataset.add_frame({CAMERA_KEY: frame, "task": task})
        dataset.save_episode()
    dataset.finalize()


def make_prompt_bank(cfg: PromptVideosConfig) -> Path:
    from lerobot.datasets.aggregate import aggregate_datasets
    from lerobot.datasets.lerobot_dataset import LeRobotDatasetMetadata
    from lerobot.utils.constants import HF_LEROBOT_HOME

    if not cfg.videos or not cfg.output_repo_id:
        raise PromptVideosError("Pass --videos=DIR_OR_GLOB and --output_repo_id=ORG/NAME_prompts.")
    out = Path(cfg.root) if cfg.root else HF_LEROBOT_HOME / cfg.output_repo_id
    if out.exists():
        meta = LeRobotDatasetMetadata(cfg.output_repo_id, root=out)
        expected = (cfg.image_size, cfg.image_size, 3)
        if set(meta.features) - {"timestamp", "frame_index", "episode_index", "index", "task_index"} != {
            CAMERA_KEY
        }:
            raise PromptVideosError(
                f"{out} has the features {sorted(meta.features)}; jept-prompts adds to banks it wrote itself "
                f"(only {CAMERA_KEY}). Write to another --output_repo_id."
            )
        if tuple(meta.features[CAMERA_KEY]["shape"]) != expected or meta.fps != cfg.fps:
            raise PromptVideosError(
                f"{out} holds {tuple(meta.features[CAMERA_KEY]['shape'])} frames at {meta.fps} fps; pass "
                f"--image_size={meta.features[CAMERA_KEY]['shape'][0]} --fps={meta.fps} to add to it."
            )
    files = find_videos(cfg)
    videos = [
        (read_video(f, cfg.fps, cfg.image_size), task)
        for f, task in tqdm(files, desc="decoding", unit="video")
    ]
    staging = out.with_name(out.name + ".staging")
    shutil.rmtree(staging, ignore_errors=True)
    write_bank(cfg, videos, staging / "new")
    if out.exists():  # add to the bank: LeRobot's aggregation of the old and the new episodes
        aggregate_datasets(
            repo_ids=[cfg.output_repo_id, cfg.output_repo_id],
            aggr_repo_id=cfg.output_repo_id,
            roots=[out, staging / "new"],
            aggr_root=staging / "merged",
        )
        result = staging / "merged"
    else:
        result = staging / "new"
    old = out.with_name(out.name + ".old")
    if out.exists():
        out.rename(old)
    result.rename(out)
    shutil.rmtree(old, ignore_errors=True)
    shutil.rmtree(staging, ignore_errors=True)
    tasks = sorted({t for _, t in files})
    print(f"Wrote {len(files)} prompt videos ({', '.join(tasks)}) to {cfg.output_repo_id} ({out}).")
    if cfg.push_to_hub:
        push_dataset(cfg.output_repo_id, out, ["jept", "prompts"], cfg.private, PromptVideosError)
    return out


def main() -> None:
    logging.basicConfig(level=logging.WARNING)
    cfg = draccus.parse(PromptVideosConfig)
    try:
        make_prompt_bank(cfg)
    except PromptVideosError as err:
        sys.exit(f"jept-prompts: {err}")
