"""Prompt banks: LeRobotDatasets whose episodes are prompt videos, looked up by the task string.

The builder writes one as ``ORG/NAME_prompts``. A prompt is the episode's camera frames, uniformly subsampled to
at most ``max_frames`` and resized to the model's resolution; decoded prompts are cached in memory (uint8).
"""

import logging
from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F  # noqa: N812
from lerobot.datasets.lerobot_dataset import LeRobotDataset
from lerobot.datasets.video_utils import decode_video_frames, get_video_duration_in_s, get_video_info
from torch import Tensor


class PromptNotFoundError(KeyError):
    def __str__(self) -> str:  # KeyError would print the message in quotes
        return str(self.args[0])


def subsample_indices(length: int, max_frames: int) -> np.ndarray:
    """At most ``max_frames`` indices spread uniformly over ``range(length)``, first and last included."""
    if length <= max_frames:
        return np.arange(length)
    return np.rint(np.linspace(0, length - 1, max_frames)).astype(np.int64)


def unit_float(frames: Tensor) -> Tensor:
    """uint8 frames (0-255, as bank prompts travel) as float32 in [0, 1]; floating-point frames as given."""
    return frames.float() / 255 if frames.dtype == torch.uint8 else frames


def resize_frames(frames: Tensor, size: int) -> Tensor:
    """(N, 3, H, W) float in [0, 1] -> (N, 3, size, size)."""
    if frames.shape[-2:] == (size, size):
        return frames
    return F.interpolate(frames, size=(size, size), mode="bilinear", antialias=True, align_corners=False)


def as_uint8(frames: Tensor, size: int) -> Tensor:
    """(N, 3, H, W) float frames in [0, 1] -> (N, 3, size, size) uint8 (how decoded prompts are kept)."""
    return (resize_frames(frames.float(), size) * 255).round().clamp(0, 255).to(torch.uint8)


def load_prompt_video(path: str | Path, max_frames: int, image_size: int) -> Tensor:
    """(N, 3, size, size) uint8 frames of a prompt video file (any format FFmpeg reads), uniformly subsampled to
    at most ``max_frames``, decoded with LeRobot's own video decoding."""
    path = Path(path).expanduser()
    if not path.is_file():
        raise FileNotFoundError(
            f"Prompt video {str(path)!r} does not exist: --policy.prompt_video takes the path of a video file "
            "showing the task (e.g. an .mp4 recorded by any camera)."
        )
    fps = get_video_info(path).get("video.fps")
    if not fps:
        raise ValueError(f"Prompt video {path} has no video stream: give a video file that FFmpeg can read.")
    length = max(1, int(get_video_duration_in_s(path) * fps + 1e-6))
    timestamps = [float(i / fps) for i in subsample_indices(length, max_frames)]
    frames = decode_video_frames(path, timestamps, tolerance_s=1 / fps - 1e-4)
    return as_uint8(frames, image_size)


class PromptBank:
    """Prompt videos of a LeRobotDataset, by task string."""

    def __init__(self, repo_id: str, root: str | None, max_frames: int, image_size: int):
        self.repo_id, self.root, self.max_frames, self.image_size = repo_id, root, max_frames, image_size
        self.dataset = LeRobotDataset(repo_id, root=root)
        meta = self.dataset.meta
        if not meta.video_keys and not meta.camera_keys:
            raise ValueError(f"Prompt bank {repo_id} has no camera feature: it cannot hold prompt videos.")
        self.camera_key = (meta.video_keys or meta.camera_keys)[0]
        self.episodes_by_task: dict[str, list[int]] = {}
        for ep in range(meta.total_episodes):
            for task in meta.episodes[ep]["tasks"]:
                self.episodes_by_task.setdefault(task, []).append(ep)
        self._cache: dict[int, Tensor] = {}

    @property
    def tasks(self) -> list[str]:
        return sorted(self.episodes_by_task)

    def episodes(self, task: str) -> list[int]:
        if task not in self.episodes_by_task:
            raise PromptNotFoundError(
                f"No prompt video for task {task!r} in the prompt bank {self.repo_id}, which has prompts for "
                f"{self.tasks}. Build the bank with that task (jept-build-metaworld --unseen_tasks=...) or pass "
                "the prompt video as `observation.prompt_video`."
            )
        return self.episodes_by_task[task]

    def video(self, episode: int) -> Tensor:
        """(N, 3, size, size) uint8 frames of one prompt episode, decoded once."""
        if episode not in self._cache:
            self._cache[episode] = self._decode(episode)
        return self._cache[episode]

    def _decode(self, episode: int) -> Tensor:
        meta = self.dataset.meta
        ep = meta.episodes[episode]
        keep = subsample_indices(ep["length"], self.max_frames)
        if self.camera_key in meta.video_keys:
            start = ep[f"videos/{self.camera_key}/from_timestamp"]
            timestamps = [float(start + i / meta.fps) for i in keep]
            path = self.dataset.root / meta.get_video_file_path(episode, self.camera_key)
            frames = decode_video_frames(path, timestamps, 1 / meta.fps - 1e-4)
        else:
            first = ep["dataset_from_index"]
            frames = torch.stack([self.dataset[int(first + i)][self.camera_key] for i in keep])
        logging.debug("Decoded prompt episode %d of %s: %d frames", episode, self.repo_id, len(keep))
        return as_uint8(frames, self.image_size)

    def batch(self, episodes: list[int], as_uint8: bool = False) -> tuple[Tensor, Tensor]:
        """Prompt videos (B, N, 3, H, W) float in [0, 1] (``as_uint8``: the decoded uint8 frames, a quarter of
        the memory; the policies convert them frame chunk by frame chunk), padded to the longest, and masks
        (B, N), True = real."""
        videos = [self.video(ep) for ep in episodes]
        n = max(len(v) for v in videos)
        dtype = torch.uint8 if as_uint8 else torch.float32
        out = torch.zeros(len(videos), n, 3, self.image_size, self.image_size, dtype=dtype)
        mask = torch.zeros(len(videos), n, dtype=torch.bool)
        for i, v in enumerate(videos):
            out[i, : len(v)] = v if as_uint8 else unit_float(v)
            mask[i, : len(v)] = True
        return out, mask
