"""``--env.type=jept_metaworld``: Meta-World under the paper's protocol, for ``lerobot-eval``.

The env is :class:`~lerobot_jept.envs.metaworld.JeptMetaworldEnv`, the same class the builder records with, so
evaluation sees exactly the dataset's observations (camera, image size, self-state, action repeat, truncation).
With ``prompt_repo_id`` it hands the policy the episode's prompt video as ``observation.prompt_video``.
"""

from dataclasses import dataclass, field

import gymnasium as gym
from lerobot.configs.types import FeatureType, PolicyFeature
from lerobot.envs.configs import EnvConfig, _make_vec_env_cls
from lerobot.processor import PolicyProcessorPipeline, ProcessorStep, TransitionKey
from lerobot.utils.constants import ACTION, OBS_IMAGE, OBS_STATE

from lerobot_jept.envs.metaworld import ACTION_DIM, STATE_DIM, JeptMetaworldEnv, check_task

PROMPT_VIDEO, PROMPT_MASK = "observation.prompt_video", "observation.prompt_video_mask"


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


@EnvConfig.register_subclass("jept_metaworld")
@dataclass
class JeptMetaworldEnvConfig(EnvConfig):
    """Args:
    task: a Meta-World v3 task, or several separated by commas (each is its own group in eval_info.json).
    image_size, action_repeat, episode_length: must match the dataset (the builder's ``--image_size``;
        the paper's 2 and 250).
    prompt_repo_id, prompt_root: the prompt bank, e.g. the builder's ``ORG/NAME_prompts``.
    prompt_max_frames: prompt frames per episode; use the policy's ``max_prompt_length``.
    """

    task: str = "button-press-v3"
    fps: int = 40
    image_size: int = 224
    action_repeat: int = 2
    episode_length: int = 250
    prompt_repo_id: str | None = None
    prompt_root: str | None = None
    prompt_max_frames: int = 250
    features: dict[str, PolicyFeature] = field(default_factory=dict)
    features_map: dict[str, str] = field(
        default_factory=lambda: {ACTION: ACTION, "agent_pos": OBS_STATE, "pixels": OBS_IMAGE}
    )

    def __post_init__(self):
        self.features = {
            ACTION: PolicyFeature(type=FeatureType.ACTION, shape=(ACTION_DIM,)),
            "agent_pos": PolicyFeature(type=FeatureType.STATE, shape=(STATE_DIM,)),
            "pixels": PolicyFeature(type=FeatureType.VISUAL, shape=(self.image_size, self.image_size, 3)),
        }
        for task in self.tasks:
            check_task(task)
        self.fps = 80 // self.action_repeat

    @property
    def tasks(self) -> list[str]:
        return [t.strip() for t in (self.task or "").split(",") if t.strip()]

    @property
    def gym_kwargs(self) -> dict:
        return {
            "image_size": self.image_size,
            "action_repeat": self.action_repeat,
            "max_episode_steps": self.episode_length,
            "prompt_repo_id": self.prompt_repo_id,
            "prompt_root": self.prompt_root,
            "prompt_max_frames": self.prompt_max_frames,
        }

    def create_envs(
        self, n_envs: int, use_async_envs: bool = False
    ) -> dict[str, dict[int, gym.vector.VectorEnv]]:
        env_cls = _make_vec_env_cls(use_async_envs, n_envs)
        kwargs = {"context": "forkserver"} if env_cls is gym.vector.AsyncVectorEnv else {}
        out = {}
        for task in self.tasks:
            fns = [lambda t=task: JeptMetaworldEnv(t, **self.gym_kwargs) for _ in range(n_envs)]
            out[task] = {0: env_cls(fns, autoreset_mode=gym.vector.AutoresetMode.SAME_STEP, **kwargs)}
        return out

    def get_env_processors(self):
        return PolicyProcessorPipeline(steps=[PromptVideoLayoutStep()]), PolicyProcessorPipeline(steps=[])
