"""The env types of ``lerobot-eval``: ``--env.type=jept_metaworld`` and ``--env.type=jept_robosuite``.

Each builds the very env class its builder records with, so evaluation sees exactly the dataset's
observations, and with ``--env.prompt_repo_id`` hands the policy the episode's prompt video as
``observation.prompt_video`` (see :mod:`lerobot_jept.envs.prompting`).
"""

from dataclasses import dataclass

from lerobot.envs.configs import EnvConfig

from lerobot_jept.envs import metaworld as mw
from lerobot_jept.envs import robosuite as rs
from lerobot_jept.envs.prompting import JeptEnvConfig


@EnvConfig.register_subclass("jept_metaworld")
@dataclass
class JeptMetaworldEnvConfig(JeptEnvConfig):
    """Meta-World under the paper's protocol (Appendix B.1): ``task`` is a v3 task name; ``action_repeat`` 2
    and ``episode_length`` 250 as in the paper."""

    ACTION_DIM = mw.ACTION_DIM
    STATE_DIM = mw.STATE_DIM

    task: str = "button-press-v3"
    fps: int = 40
    action_repeat: int = 2
    episode_length: int = 250

    def __post_init__(self):
        super().__post_init__()
        self.fps = mw.PHYSICS_FPS // self.action_repeat

    def check_task(self, task: str) -> None:
        mw.check_task(task)

    def describe(self, task: str) -> str:
        return mw.task_description(task)

    def make_one(self, task: str) -> mw.JeptMetaworldEnv:
        return mw.JeptMetaworldEnv(
            task,
            image_size=self.image_size,
            action_repeat=self.action_repeat,
            max_episode_steps=self.episode_length,
        )


@EnvConfig.register_subclass("jept_robosuite")
@dataclass
class JeptRobosuiteEnvConfig(JeptEnvConfig):
    """robosuite under the paper's protocol (Section 4.3): ``task`` is ``<prompt arm>-<manipulation>``
    (``sawyer-lift``); a Panda executes, the prompt shows the prompt arm; ``episode_length`` 200."""

    ACTION_DIM = rs.ACTION_DIM
    STATE_DIM = rs.STATE_DIM

    task: str = "panda-lift"
    fps: int = rs.CONTROL_FREQ
    episode_length: int = 200

    def check_task(self, task: str) -> None:
        rs.check_task(task)

    def describe(self, task: str) -> str:
        return rs.task_description(task)

    def make_one(self, task: str) -> rs.JeptRobosuiteEnv:
        return rs.JeptRobosuiteEnv(task, image_size=self.image_size, max_episode_steps=self.episode_length)
