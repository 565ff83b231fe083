"""Prompt videos for evaluation envs, and the ``lerobot-eval`` env configs built on them.

:class:`PromptVideoWrapper` gives each episode of a JEPT env a prompt: prompt ``seed % num_prompts`` of the
task from a prompt bank, so 50 seeded episodes over 10 prompts are the paper's "10 prompt videos x 5 seeds",
exactly and reproducibly; the env's processor (:class:`PromptVideoFromBankStep`) hands the video to the policy
on the episode's first step only. :class:`JeptEnvConfig` is what ``jept_metaworld`` and
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

PROMPT_VIDEO, PROMPT_MASK = "observation.prompt_video", "observation.prompt_video_mask"
PROMPT_EPISODE, PROMPT_NEW = "observation.prompt_episode", "observation.prompt_new"


class PromptVideoWrapper(gym.Wrapper):
    """Adds the episode's prompt to the observations as ``prompt_episode`` (1,) int64, the episode of the
    prompt bank shown, and ``prompt_new`` (1,) uint8, 1 on the first observation of an episode: prompts of
    the env's own task, or of the task described by ``prompt_description`` (another task's video).

    The video itself crosses to the policy once per episode: :class:`PromptVideoFromBankStep`, the env's
    processor, decodes it from the same bank and attaches it when ``prompt_new`` is set (the policy encodes a
    prompt once per episode), so a control step does not carry 250 frames through LeRobot's observation path.
    :meth:`prompt_video` gives the frames of the current episode's prompt.
    """

    def __init__(
        self,
        env: gym.Env,
        repo_id: str,
        root: str | None,
        max_frames: int,
        prompt_description: str | None = None,
    ):
        from lerobot_jept.policies.prompts import (
            PromptBank,  # LeRobot's datasets: loaded when an env is built
        )

        super().__init__(env)
        self.bank = PromptBank(repo_id, root, max_frames, env.unwrapped.image_size)
        self.episodes = self.bank.episodes(prompt_description or env.unwrapped.task_description)
        self.observation_space = spaces.Dict(
            {
                **env.observation_space.spaces,
                "prompt_episode": spaces.Box(0, np.iinfo(np.int32).max, (1,), np.int64),
                "prompt_new": spaces.Box(0, 1, (1,), np.uint8),
            }
        )
        self.prompt_episode: int | None = None
        self._resets = 0

    @property
    def task_description(self) -> str:
        return self.env.unwrapped.task_description

    def prompt_video(self) -> np.ndarray:
        """(N, H, W, 3) uint8 frames of the current episode's prompt."""
        return self.bank.video(self.prompt_episode).permute(0, 2, 3, 1).numpy()

    def _observation(self, obs: dict, new: bool) -> dict:
        prompt = {"prompt_episode": np.array([self.prompt_episode]), "prompt_new": np.array([new], np.uint8)}
        return {**obs, **prompt}

    def reset(self, *, seed: int | None = None, options: dict | None = None):
        """Prompt ``seed % num_prompts`` of the task (the next one in turn when reset without a seed)."""
        obs, info = self.env.reset(seed=seed, options=options)
        index = seed if seed is not None else self._resets
        self.prompt_episode = self.episodes[index % len(self.episodes)]
        self._resets += 1
        return self._observation(obs, True), info

    def step(self, action):
        obs, reward, terminated, truncated, info = self.env.step(action)
        return self._observation(obs, False), reward, terminated, truncated, info


class PromptVideoFromBankStep(ProcessorStep):
    """The env's processor: on an episode's first observation (``prompt_new``), the prompt video of each env
    (``prompt_episode`` of the bank) as (B, N, 3, H, W) uint8 with its (B, N) frame mask; on the others,
    nothing (the policy keeps the episode's prompt encoding). Decoded prompts are cached by the bank."""

    def __init__(self, repo_id: str, root: str | None, max_frames: int, image_size: int):
        self.repo_id, self.root, self.max_frames, self.image_size = repo_id, root, max_frames, image_size
        self._bank = None

    def __call__(self, transition):
        observation = dict(transition.get(TransitionKey.OBSERVATION) or {})
        episode, new = observation.pop(PROMPT_EPISODE, None), observation.pop(PROMPT_NEW, None)
        if episode is not None and bool((new > 0.5).any()):
            if self._bank is None:
                from lerobot_jept.policies.prompts import PromptBank

                self._bank = PromptBank(self.repo_id, self.root, self.max_frames, self.image_size)
            episodes = [int(e) for e in episode.reshape(-1).tolist()]
            observation[PROMPT_VIDEO], observation[PROMPT_MASK] = self._bank.batch(episodes, as_uint8=True)
        new_transition = dict(transition)
        new_transition[TransitionKey.OBSERVATION] = observation
        return new_transition

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
        steps = []
        if self.prompt_repo_id is not None:
            steps.append(
                PromptVideoFromBankStep(
                    self.prompt_repo_id, self.prompt_root, self.prompt_max_frames, self.image_size
                )
            )
        return PolicyProcessorPipeline(steps=steps), PolicyProcessorPipeline(steps=[])
