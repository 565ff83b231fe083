"""`jept-build-robosuite`: robosuite expert rollouts as LeRobotDataset repos for JEPT (paper, Section 4.3).

A Panda arm executes every task (demos, videos); prompt videos show the task's prompt arm doing the same
manipulation. Example (tiny)::

    jept-build-robosuite --repo_id=local/rs_tiny --demo_tasks='[panda-stack]' --video_tasks='[sawyer-stack]' \
        --unseen_tasks='[ur5e-lift]' --episodes_per_task=4 --prompts_per_task=2 --image_size=64
"""

import logging
from dataclasses import dataclass, field

import draccus

from dataset_builders.core import BuildConfig, BuildError, Simulator, build
from lerobot_jept.envs import robosuite as rs

# The paper's Table 8 structure with core robosuite 1.5.2 tasks (see README): Stack prompted by each arm plus two
# PickPlaceCan tasks are demonstrated, NutAssemblySquare prompted by each arm plus one more PickPlaceCan task are
# video-only, Lift prompted by each arm is unseen.
DEFAULT_DEMO_TASKS = [f"{arm}-stack" for arm in rs.ARMS] + ["panda-can", "ur5e-can"]
DEFAULT_VIDEO_TASKS = [f"{arm}-square" for arm in rs.ARMS] + ["iiwa-can"]
DEFAULT_UNSEEN_TASKS = [f"{arm}-lift" for arm in rs.ARMS]


@dataclass
class RobosuiteBuildConfig(BuildConfig):
    repo_id: str = "local/jept_robosuite"
    demo_tasks: list[str] = field(default_factory=lambda: list(DEFAULT_DEMO_TASKS))
    video_tasks: list[str] = field(default_factory=lambda: list(DEFAULT_VIDEO_TASKS))
    unseen_tasks: list[str] = field(default_factory=lambda: list(DEFAULT_UNSEEN_TASKS))
    episodes_per_task: int = 1000
    action_repeat: int = 1
    max_episode_steps: int = 200


class RobosuiteSimulator(Simulator):
    name = "robosuite"
    robot_type = rs.ROBOT_TYPE

    def check_task(self, task: str) -> str:
        try:
            return rs.check_task(task)
        except ValueError as err:
            raise BuildError(str(err)) from None

    def task_description(self, task: str) -> str:
        return rs.task_description(task)

    def make_env(self, task: str, cfg: BuildConfig, role: str = "demo") -> rs.JeptRobosuiteEnv:
        return rs.JeptRobosuiteEnv(
            task,
            image_size=cfg.image_size,
            max_episode_steps=cfg.max_episode_steps,
            embodiment="prompt" if role == "prompts" else "panda",
        )

    def fps(self, cfg: BuildConfig) -> int:
        return rs.CONTROL_FREQ

    def observation_features(self, cfg: BuildConfig) -> dict:
        return rs.observation_features(cfg.image_size)

    def action_feature(self) -> dict:
        return rs.action_feature()


def main(args: list[str] | None = None) -> None:
    logging.basicConfig(level=logging.WARNING)
    cfg = draccus.parse(config_class=RobosuiteBuildConfig, args=args)
    try:
        if cfg.action_repeat != 1:
            raise BuildError(
                "robosuite's controller runs at 20 Hz, one step per action: pass --action_repeat=1."
            )
        build(cfg, RobosuiteSimulator())
    except BuildError as err:
        raise SystemExit(f"jept-build-robosuite: error: {err}") from None


if __name__ == "__main__":
    main()
