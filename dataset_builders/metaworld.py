"""`jept-build-metaworld`: Meta-World expert rollouts as LeRobotDataset repos for JEPT (paper, Appendix B).

Example (a tiny build; the defaults reproduce the paper's Table 7 split at 500 episodes per task)::

    jept-build-metaworld --repo_id=local/mw_tiny --demo_tasks='[button-press-v3]' \
        --video_tasks='[drawer-close-v3]' --unseen_tasks='[handle-press-v3]' \
        --episodes_per_task=4 --prompts_per_task=2 --image_size=64
"""

import logging
from dataclasses import dataclass, field

import draccus

from dataset_builders.config import PLAY_POLICIES
from dataset_builders.core import BuildConfig, BuildError, Simulator, build
from lerobot_jept.envs import metaworld as mw


@dataclass
class MetaworldBuildConfig(BuildConfig):
    repo_id: str = "local/jept_metaworld"
    demo_tasks: list[str] = field(default_factory=lambda: list(mw.TABLE7_DEMO_TASKS))
    video_tasks: list[str] = field(default_factory=lambda: list(mw.TABLE7_VIDEO_TASKS))
    unseen_tasks: list[str] = field(default_factory=lambda: list(mw.TABLE7_UNSEEN_TASKS))
    episodes_per_task: int = 500
    max_episode_steps: int = 250


class MetaworldSimulator(Simulator):
    name = "metaworld"
    robot_type = mw.ROBOT_TYPE
    play_policies = PLAY_POLICIES

    def check_task(self, task: str) -> str:
        try:
            return mw.check_task(task)
        except ValueError as err:
            raise BuildError(str(err)) from None

    def task_description(self, task: str) -> str:
        return mw.task_description(task)

    def make_env(self, task: str, cfg: BuildConfig, role: str = "demo") -> mw.JeptMetaworldEnv:
        return mw.JeptMetaworldEnv(
            task,
            image_size=cfg.image_size,
            action_repeat=cfg.action_repeat,
            max_episode_steps=cfg.max_episode_steps,
        )

    def fps(self, cfg: BuildConfig) -> int:
        return mw.PHYSICS_FPS // cfg.action_repeat

    def observation_features(self, cfg: BuildConfig) -> dict:
        return mw.observation_features(cfg.image_size)

    def action_feature(self) -> dict:
        return mw.action_feature()


def main(args: list[str] | None = None) -> None:
    logging.basicConfig(level=logging.WARNING)
    cfg = draccus.parse(config_class=MetaworldBuildConfig, args=args)
    try:
        build(cfg, MetaworldSimulator())
    except BuildError as err:
        raise SystemExit(f"jept-build-metaworld: error: {err}") from None


if __name__ == "__main__":
    main()
