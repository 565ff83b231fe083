"""Prompt videos for evaluation envs, and the ``lerobot-eval`` env configs built on them.

:class:`PromptVideoWrapper` adds the episode's prompt video to every observation of a JEPT env: prompt
``seed % num_prompts`` of the task from a prompt bank, so 50 seeded episodes over 10 prompts are the paper's
"10 prompt videos x 5 seeds", exactly and reproducibly. :class:`JeptEnvConfig` is what ``jept_metaworld`` and
``jept_robosuite`` share.
"""

import abc
from dataclasses import dataclass, field
from typing import ClassVar

import gymnasium as gym
import numpy as np
from gymnasium import spaces
from lerobot.configs.types import FeatureType, PolicyFeature
from lerobot.envs.configs import EnvConfig, _make_vec_env_cls
from lerobot.processor import PolicyProcessorPipeline, ProcessorStep, TransitionKey
from lerobot.utils.constants import ACTION, OBS_IMAGE, OBS_STATE

from lerobot_jept.prompts import PromptBank

PROMPT_VIDEO, PROMPT_MASK = "observation.prompt_video", "observation.prompt_video_mask"


class PromptVideoWrapper(gym.Wrapper):
    """Adds ``prompt_video`` (N, H, W, 3) uint8 and ``prompt_video_mask`` (N,) to the observations: prompts of
    the env's own task, or of the task described by ``prompt_description`` (another task's video)."""

    def __init__(
        self,
        env: gym.Env,
        repo_id: str,
        root: str | None,
        max_frames: int,
        prompt_description: str | None = None,
    ):
        super().__init__(env)
        size = env.unwrapped.image_size
        self.bank = PromptBank(repo_id, root, max_frames, size)
        self.episodes = self.bank.episodes(prompt_description or env.unwrapped.task_description)
        self.max_frames = max_frames
        self.observation_space = spaces.Dict(
            {
                **env.observation_space.spaces,
                "prompt_video": spaces.Box(0, 255, (max_frames, size, size, 3), np.uint8),
                "prompt_video_mask": spaces.Box(0, 1, (max_frames,), np.uint8),
            }
        )
        self.prompt_episode: int | None = None
        self._resets = 0
        self._arrays = None

    @property
    def task_description(self) -> str:
        return self.env.unwrapped.task_description

    def _choose(self, seed: int | None) -> None:
        """Prompt ``seed % num_prompts`` of the task (the next one in turn when reset without a seed)."""
        index = seed if seed is not None else self._resets
        self.prompt_episode = self.episodes[index % len(self.episodes)]
        frames = self.bank.video(self.prompt_episode).permute(0, 2, 3, 1).numpy()
        video = np.zeros(self.observation_space["prompt_video"].shape, np.uint8)
        mask = np.zeros(self.max_frames, np.uint8)
        video[: len(frames)], mask[: len(frames)] = frames, 1
        self._arrays = {"prompt_video": video, "prompt_video_mask": mask}

    def reset(self, *, seed: int | None = None, options: dict | None = None):
        obs, info = self.env.reset(seed=seed, options=options)
        self._choose(seed)
        self._resets += 1
        return {**obs, **self._arrays}, info

    def step(self, action):
        obs, reward, terminated, truncated, info = self.env.step(action)
        return {**obs, **self._arrays}, reward, terminated, truncated, info


class PromptVideoLayoutStep(ProcessorStep):
    """The env's prompt video, (B, N, H, W, 3) in 0..255 after LeRobot's generic conversion, to the policy's
    (B, N, 3, H, W) in [0, 1]; the frame mask to bool."""

    def __call__(self, transition):
        observation = dict(transition.get(TransitionKey.OBSERVATION) or {})
        if PROMPT_VIDEO in observation:
            video = observation[PROMPT_VIDEO]
            if video.ndim == 4:
                video = video[None]
            observation[PROMPT_VIDEO] = video.permute(0, 1, 4, 2, 3).float() / 255
            if PROMPT_MASK in observation:
                observation[PROMPT_MASK] = observation[PROMPT_MASK].reshape(video.shape[:2]) > 0.5
        new = dict(transition)
        new[TransitionKey.OBSERVATION] = observation
        return new

    def transform_features(self, features):
        return features


@dataclass
class JeptEnvConfig(EnvConfig):
    """What the JEPT env types share: comma-separated tasks (one eval group each), the builder's observation
    (``pixels`` -> ``observation.image``, ``agent_pos`` -> ``observation.state``) and the prompt bank.

    Args:
        task: one task, or several separated by commas.
        image_size, episode_length: must match the dataset (the builder's ``--image_size``, ``--max_episode_steps``).
        prompt_repo_id, prompt_root: the prompt bank, e.g. the builder's ``ORG/NAME_prompts``.
        prompt_max_frames: prompt frames per episode; use the policy's ``max_prompt_length``.
        prompt_task: show every episode the bank prompts of this task instead of the env task's own (e.g. its
            scene-mate's: window-close's video in the window-open env), to see whether the policy does what the
            video shows. Default: the env task's own.
    """

    image_size: int = 224
    prompt_repo_id: str | None = None
    prompt_root: str | None = None
    prompt_max_frames: int = 250
    prompt_task: str | None = None
    features: dict[str, PolicyFeature] = field(default_factory=dict)
    features_map: dict[str, str] = field(
        default_factory=lambda: {ACTION: ACTION, "agent_pos": OBS_STATE, "pixels": OBS_IMAGE}
    )

    ACTION_DIM: ClassVar[int]  # set by each env type
    STATE_DIM: ClassVar[int]

    def __post_init__(self):
        self.features = {
            ACTION: PolicyFeature(type=FeatureType.ACTION, shape=(self.ACTION_DIM,)),
            "agent_pos": PolicyFeature(type=FeatureType.STATE, shape=(self.STATE_DIM,)),
            "pixels": PolicyFeature(type=FeatureType.VISUAL, shape=(self.image_size, self.image_size, 3)),
        }
        for task in self.tasks:
            self.check_task(task)
        if self.prompt_task is not None:
            self.check_task(self.prompt_task)
            if self.prompt_repo_id is None:
                raise ValueError(
                    f"--env.prompt_task={self.prompt_task} shows that task's prompt videos: pass the bank that has "
                    "them with --env.prompt_repo_id=ORG/NAME_prompts."
                )

    @property
    def tasks(self) -> list[str]:
        return [t.strip() for t in (self.task or "").split(",") if t.strip()]

    @abc.abstractmethod
    def check_task(self, task: str) -> None:
        """Raise ValueError (naming close matches) for a task the env type does not have."""

    @abc.abstractmethod
    def make_one(self, task: str) -> gym.Env:
        """The bare env of one task (the builder's)."""

    @abc.abstractmethod
    def describe(self, task: str) -> str:
        """The task's description: the task string of its episodes in the builder's repos."""

    def make_prompted(self, task: str) -> gym.Env:
        env = self.make_one(task)
        if self.prompt_repo_id is None:
            return env
        shown = self.describe(self.prompt_task) if self.prompt_task else None
        return PromptVideoWrapper(env, self.prompt_repo_id, self.prompt_root, self.prompt_max_frames, shown)

    @property
    def gym_kwargs(self) -> dict:
        return {}

    def create_envs(
        self, n_envs: int, use_async_envs: bool = False
    ) -> dict[str, dict[int, gym.vector.VectorEnv]]:
        env_cls = _make_vec_env_cls(use_async_envs, n_envs)
        kwargs = {"context": "forkserver"} if env_cls is gym.vector.AsyncVectorEnv else {}
        out = {}
        for task in self.tasks:
            fns = [lambda t=task: self.make_prompted(t) for _ in range(n_envs)]
            out[task] = {0: env_cls(fns, autoreset_mode=gym.vector.AutoresetMode.SAME_STEP, **kwargs)}
        return out

    def get_env_processors(self):
        return PolicyProcessorPipeline(steps=[PromptVideoLayoutStep()]), PolicyProcessorPipeline(steps=[])
