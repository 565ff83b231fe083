"""``make_jept_pre_post_processors``: LeRobot's standard steps plus JEPT's own two.

Preprocessor: ``rename_observations_processor`` -> ``to_batch_processor`` -> ``jept_prompt_video`` ->
``device_processor`` -> ``normalizer_processor`` -> ``jept_action_bins``. Postprocessor:
``unnormalizer_processor`` -> ``device_processor`` (cpu). Both JEPT steps serialise their parameters with the
checkpoint (``get_config``).
"""

import logging
import zlib
from dataclasses import dataclass, field
from typing import Any

import torch
from lerobot.processor import (
    PolicyAction,
    PolicyProcessorPipeline,
    ProcessorStep,
    ProcessorStepRegistry,
    TransitionKey,
)
from lerobot.processor.factory import make_default_policy_processor_steps, make_policy_processor_pipelines
from torch import Tensor

from lerobot_jept.envs.spec import ACTION_LABELLED
from lerobot_jept.policies.configuration import VideoPolicyConfig
from lerobot_jept.policies.jept.modeling_jept import IGNORE_INDEX, PROMPT_ID, PROMPT_MASK, PROMPT_VIDEO
from lerobot_jept.policies.prompts import PromptBank, resize_frames, subsample_indices, unit_float


@ProcessorStepRegistry.register("jept_action_bins")
@dataclass
class JeptActionBinsStep(ProcessorStep):
    """Continuous ``action`` -> bin indices (long) over [low, high]; unlabelled frames -> IGNORE_INDEX.

    A frame is unlabelled where ``observation.action_labelled`` is 0 (mixes, see ``lerobot_jept.datasets.mixing``; the
    key is removed here, it is not a model input; its window of frames starts where the action's does) or
    where the action is NaN (mixes of format 1). Values outside the range are clipped into the end bins and
    counted (``num_clipped`` of ``num_values``). A transition without an action (inference) passes through.
    """

    num_bins: int = 7
    low: float | list[float] = -1.0
    high: float | list[float] = 1.0
    num_clipped: int = field(default=0, init=False)
    num_values: int = field(default=0, init=False)

    def __call__(self, transition):
        observation = transition.get(TransitionKey.OBSERVATION) or {}
        labelled = observation.get(ACTION_LABELLED)
        if labelled is not None:
            transition = dict(transition)
            transition[TransitionKey.OBSERVATION] = {
                k: v for k, v in observation.items() if k != ACTION_LABELLED
            }
        action = transition.get(TransitionKey.ACTION)
        if action is None or not torch.is_tensor(action) or not action.is_floating_point():
            return transition
        finite = torch.isfinite(action)
        if labelled is not None:  # (B, T_obs, 1) or (B, 1): the action's frames are its first T_act
            steps = action.shape[1] if action.ndim == 3 else 1
            mask = labelled.reshape(labelled.shape[0], -1)[:, :steps] > 0.5
            finite = finite & mask.reshape(*action.shape[:-1], 1).to(finite.device)
        low = torch.as_tensor(self.low, dtype=action.dtype, device=action.device)
        high = torch.as_tensor(self.high, dtype=action.dtype, device=action.device)
        outside = finite & ((action < low) | (action > high))
        clipped = int(outside.sum())
        if clipped and not self.num_clipped:
            logging.warning(
                "jept_action_bins: %d action values lie outside [%s, %s] and are clipped into the end bins; "
                "set --policy.action_low/--policy.action_high to the env's action range, or "
                "--policy.action_range=dataset for each dimension's range in the data (absolute actions).",
                clipped,
                self.low,
                self.high,
            )
        self.num_clipped += clipped
        self.num_values += int(finite.sum())
        scaled = (torch.clamp(action, low, high) - low) / (high - low) * (self.num_bins - 1)
        bins = torch.where(finite, scaled.round(), torch.full_like(scaled, IGNORE_INDEX)).long()
        new = dict(transition)
        new[TransitionKey.ACTION] = bins
        return new

    def get_config(self) -> dict[str, Any]:
        return {"num_bins": self.num_bins, "low": self.low, "high": self.high}

    def transform_features(self, features):
        return features


@ProcessorStepRegistry.register("jept_prompt_video")
@dataclass
class JeptPromptVideoStep(ProcessorStep):
    """Attach the prompt video ``observation.prompt_video`` (B, N, 3, H, W) in [0, 1] and its frame mask.

    A prompt given by the caller (or the env) is kept, resized to ``image_size`` if needed. Dataset samples
    (they carry an ``index``) get a random prompt of their task from the prompt bank ``repo_id``. Anything else
    (control) passes through: the policy then takes the prompt its own config names (``prompt_video``, else
    ``prompt_repo_id``), so options given at evaluation or rollout apply to a saved pipeline. ``root`` (a
    local folder) is never saved with the pipeline.
    """

    repo_id: str | None = None
    root: str | None = None
    max_frames: int = 250
    image_size: int = 224
    _bank: PromptBank | None = field(default=None, init=False, repr=False)

    @property
    def bank(self) -> PromptBank:
        if self._bank is None:
            self._bank = PromptBank(self.repo_id, self.root, self.max_frames, self.image_size)
        return self._bank

    def __call__(self, transition):
        observation = dict(transition.get(TransitionKey.OBSERVATION) or {})
        complementary = transition.get(TransitionKey.COMPLEMENTARY_DATA) or {}
        if PROMPT_VIDEO in observation:
            observation.pop(PROMPT_ID, None)  # a caller's prompt is identified by its content
            n = observation[PROMPT_VIDEO].shape[-4]
            observation[PROMPT_VIDEO] = self._as_given(observation[PROMPT_VIDEO])
            if PROMPT_MASK in observation and n > self.max_frames:
                observation[PROMPT_MASK] = observation[PROMPT_MASK][:, subsample_indices(n, self.max_frames)]
        elif "index" in complementary:
            tasks = complementary.get("task")
            if tasks is None:
                raise ValueError(
                    "jept_prompt_video: the batch has neither `observation.prompt_video` nor a `task` string "
                    "to look a prompt up by."
                )
            if self.repo_id is None:
                raise ValueError(
                    "JEPT trains on prompt videos but none was given and no prompt bank is set: pass "
                    "--policy.prompt_repo_id=ORG/NAME_prompts (built by jept-build-metaworld or jept-prompts)."
                )
            tasks = [tasks] if isinstance(tasks, str) else list(tasks)
            episodes = []
            for task in tasks:
                candidates = self.bank.episodes(task)
                episodes.append(candidates[int(torch.randint(len(candidates), ()))])
            ids = torch.tensor([self.prompt_id(ep) for ep in episodes], dtype=torch.long)
            observation[PROMPT_VIDEO], observation[PROMPT_MASK] = self.bank.batch(episodes, as_uint8=True)
            observation[PROMPT_ID] = ids
        else:
            return transition
        new = dict(transition)
        new[TransitionKey.OBSERVATION] = observation
        return new

    def prompt_id(self, episode: int) -> int:
        """The identity of a bank prompt for the policy's prompt-token cache: this bank (repo, root, frames,
        size) and the episode."""
        bank = zlib.crc32(f"{self.repo_id}|{self.root}|{self.max_frames}|{self.image_size}".encode())
        return (bank << 24) | episode

    def _as_given(self, video: Tensor) -> Tensor:
        if video.ndim == 4:
            video = video[None]
        if video.ndim != 5 or video.shape[2] != 3:
            raise ValueError(
                f"observation.prompt_video must be (B, N, 3, H, W) floats in [0, 1] or uint8, got {tuple(video.shape)}."
            )
        if video.shape[1] > self.max_frames:  # as the bank does: uniformly subsampled
            video = video[:, subsample_indices(video.shape[1], self.max_frames)]
        b, n = video.shape[:2]
        frames = resize_frames(unit_float(video.flatten(0, 1)).float(), self.image_size)
        return frames.view(b, n, 3, *([self.image_size] * 2))

    def get_config(self) -> dict[str, Any]:
        return {
            "repo_id": self.repo_id,
            "max_frames": self.max_frames,
            "image_size": self.image_size,
        }

    def transform_features(self, features):
        return features


def make_jept_pre_post_processors(
    config: VideoPolicyConfig, dataset_stats: dict[str, dict[str, Tensor]] | None = None, **kwargs
) -> tuple[
    PolicyProcessorPipeline[dict[str, Any], dict[str, Any]],
    PolicyProcessorPipeline[PolicyAction, PolicyAction],
]:
    s = make_default_policy_processor_steps(config, dataset_stats)
    prompt = JeptPromptVideoStep(
        config.prompt_repo_id, config.prompt_root, config.max_prompt_length, config.image_size
    )
    config.fit_action_range(dataset_stats)
    bins = JeptActionBinsStep(config.num_action_bins, *config.action_bounds())
    return make_policy_processor_pipelines(
        input_steps=[s.rename_observations, s.add_batch_dim, prompt, s.to_device, s.normalize, bins],
        output_steps=[s.unnormalize, s.to_cpu],
    )
