"""The one definition of a JEPT Meta-World observation, shared by the dataset builder and `jept_metaworld`.

Paper protocol (Appendix B.1): a Sawyer arm, one camera image rendered at ``image_size`` x ``image_size``,
the robot self-state (joint angles, joint velocities, end-effector position, gripper opening), an action
repeat of 2 and episodes truncated after 250 (policy) steps. The camera is LeRobot's tweaked ``corner2``
(the paper only says "customised"), and its frames are flipped upright exactly as LeRobot's own
``metaworld`` env does, so the two envs show the same picture.

:class:`JeptMetaworldEnv` is a ``gymnasium.Env`` whose observation is ``{"pixels": (H, W, 3) uint8,
"agent_pos": (18,) float32}`` (evaluation adds the prompt video with
:class:`~lerobot_jept.envs.prompting.PromptVideoWrapper`). It also exposes the task's scripted expert (:meth:`expert_action`), which the
builder uses and evaluation ignores.
"""

import atexit
import difflib
import json
from functools import cache
from pathlib import Path

import numpy as np
from gymnasium import spaces

from lerobot_jept.envs import spec
from lerobot_jept.envs.rendering import import_simulator, setup_offscreen_gl

ROBOT_TYPE = "sawyer"
ACTION_DIM = 4
ACTION_NAMES = ["dx", "dy", "dz", "grip"]
NUM_ARM_JOINTS = 7
STATE_NAMES = (
    [f"joint_pos_{i}" for i in range(NUM_ARM_JOINTS)]
    + [f"joint_vel_{i}" for i in range(NUM_ARM_JOINTS)]
    + ["eef_x", "eef_y", "eef_z", "gripper"]
)
STATE_DIM = len(STATE_NAMES)

CAMERA_NAME = "corner2"
CORNER2_POS = (0.75, 0.075, 0.7)  # LeRobot's tweak of the corner2 camera
PHYSICS_FPS = 80  # Meta-World: frame_skip 5 x timestep 2.5 ms

# Paper, Appendix B.2, Table 7: the 18-task split (8 demo, 6 video-only, 4 unseen).
TABLE7_DEMO_TASKS = [
    "button-press-v3",
    "button-press-topdown-v3",
    "handle-pull-v3",
    "reach-v3",
    "door-close-v3",
    "window-open-v3",
    "plate-slide-v3",
    "faucet-close-v3",
]
TABLE7_VIDEO_TASKS = [
    "button-press-topdown-wall-v3",
    "door-open-v3",
    "reach-wall-v3",
    "drawer-close-v3",
    "plate-slide-back-side-v3",
    "window-close-v3",
]
TABLE7_UNSEEN_TASKS = ["handle-press-v3", "lever-pull-v3", "plate-slide-back-v3", "faucet-open-v3"]


@cache
def _lerobot_metaworld_config() -> dict:
    """LeRobot's own Meta-World task table (descriptions, expert policy class per task)."""
    import lerobot.envs

    with open(Path(lerobot.envs.__file__).parent / "metaworld_config.json") as f:
        return json.load(f)


def available_tasks() -> list[str]:
    """Every Meta-World v3 task that has a task description and a scripted expert."""
    cfg = _lerobot_metaworld_config()
    return sorted(set(cfg["TASK_DESCRIPTIONS"]) & set(cfg["TASK_POLICY_MAPPING"]))


def check_task(task: str) -> str:
    """Return ``task`` if it is a known Meta-World task, else raise naming the closest matches."""
    tasks = available_tasks()
    if task not in tasks:
        close = difflib.get_close_matches(task, tasks, n=3, cutoff=0.5)
        hint = f" Did you mean {', '.join(close)}?" if close else " Task names look like 'button-press-v3'."
        raise ValueError(f"Unknown Meta-World task {task!r}.{hint}")
    return task


def task_description(task: str) -> str:
    """The task string shared by datasets, prompt banks and the env (LeRobot's Meta-World descriptions)."""
    return _lerobot_metaworld_config()["TASK_DESCRIPTIONS"][check_task(task)]


@cache
def _mt1_task(task: str):
    """The task's env class and MT1's first task (goal layout), once per process.

    ``metaworld.MT1`` builds an env and resets it 50 times to draw its goals (about a second); the envs of one
    evaluation batch share the result. It restores numpy's global random state, so skipping it changes nothing.
    """
    metaworld = import_simulator("metaworld", "metaworld")
    mt1 = metaworld.MT1(task, seed=42)
    return mt1.train_classes[task], mt1.train_tasks[0]


@cache
def scripted_expert(task: str):
    """Meta-World's scripted policy for ``task`` (the one LeRobot's Meta-World config maps it to)."""
    policies = import_simulator("metaworld.policies", "metaworld")
    return getattr(policies, _lerobot_metaworld_config()["TASK_POLICY_MAPPING"][task])()


class JeptMetaworldEnv(spec.OneImagePerState):
    """A Meta-World task under the JEPT protocol.

    Args:
        task: Meta-World v3 task name, e.g. ``"button-press-v3"``.
        image_size: side of the square camera image, rendered directly at this size.
        action_repeat: simulator steps per policy step (the paper uses 2).
        max_episode_steps: policy steps before truncation (the paper uses 250).
        fast_render: turn off MSAA, shadows and reflections (about 7x faster on a CPU renderer).

    ``step`` ends the episode (``terminated``) on success, as LeRobot's Meta-World env does.
    """

    metadata = {"render_modes": ["rgb_array"]}

    def __init__(
        self,
        task: str,
        image_size: int = 224,
        action_repeat: int = 2,
        max_episode_steps: int = 250,
        fast_render: bool = True,
    ):
        super().__init__()
        self.task = check_task(task)
        self.task_description = task_description(task)
        self.image_size = image_size
        self.action_repeat = action_repeat
        self._max_episode_steps = max_episode_steps
        self.fast_render = fast_render
        self.render_mode = "rgb_array"
        self.metadata = {**self.metadata, "render_fps": self.fps}
        self.observation_space = spec.observation_space(image_size, STATE_DIM)
        self.action_space = spaces.Box(-1.0, 1.0, (ACTION_DIM,), np.float32)
        self._env = None  # created lazily, inside the process (and GL context) that steps it
        self._viewer = None
        self._expert = None
        self._raw_obs = None
        self._steps = 0

    @property
    def fps(self) -> int:
        return PHYSICS_FPS // self.action_repeat

    def _ensure_env(self) -> None:
        if self._env is not None:
            return
        setup_offscreen_gl()
        env_class, first_task = _mt1_task(self.task)
        env = env_class(
            render_mode="rgb_array", camera_name=CAMERA_NAME, width=self.image_size, height=self.image_size
        )
        env.set_task(first_task)
        env.model.cam_pos[env.model.camera(CAMERA_NAME).id] = CORNER2_POS
        env._freeze_rand_vec = False  # a new object/goal layout at every reset ...
        env.seeded_rand_vec = True  # ... drawn from the seed given to `reset`
        if self.fast_render:
            env.model.vis.quality.offsamples = 0  # read when the render context is created, just below
        self._viewer = env.mujoco_renderer._get_viewer("rgb_array")
        if self.fast_render:
            import mujoco

            self._viewer.scn.flags[mujoco.mjtRndFlag.mjRND_SHADOW] = 0
            self._viewer.scn.flags[mujoco.mjtRndFlag.mjRND_REFLECTION] = 0
        self._expert = scripted_expert(self.task)
        self._env = env
        # Free the GL context before mujoco.egl's own exit handler (registered on first use, so it runs
        # after this one) terminates the display; freeing it later raises EGL errors at exit.
        atexit.register(self.close)

    def _draw(self) -> np.ndarray:
        # Several envs in one process each own a GL context: make ours current before drawing.
        self._viewer.make_context_current()
        return np.ascontiguousarray(np.flip(self._env.render(), (0, 1)))

    def _observation(self) -> dict:
        data = self._env.data
        state = np.concatenate(
            [data.qpos[:NUM_ARM_JOINTS], data.qvel[:NUM_ARM_JOINTS], self._raw_obs[:4]]
        ).astype(np.float32)
        return {"pixels": self.observed_image(), "agent_pos": state}

    def reset(self, seed: int | None = None, options: dict | None = None):
        self._ensure_env()
        super().reset(seed=seed)
        if seed is not None:
            self._env.seed(seed)
        self._state_changed()
        self._raw_obs, _ = self._env.reset()
        self._steps = 0
        return self._observation(), {"is_success": False}

    def step(self, action: np.ndarray):
        self._ensure_env()
        action = spec.checked_action(action, ACTION_DIM)
        reward, success = 0.0, False
        self._state_changed()
        for _ in range(self.action_repeat):
            self._raw_obs, r, _, _, info = self._env.step(action)
            reward += float(r)
            success = success or bool(info.get("success", 0.0))
            if success:
                break
        self._steps += 1
        truncated = self._steps >= self._max_episode_steps and not success
        info = {"is_success": success, "task": self.task}
        return self._observation(), reward, success, truncated, info

    def expert_action(self, task: str | None = None) -> np.ndarray:
        """The scripted expert action (continuous) for the current state: the env's own task's expert, or
        ``task``'s (e.g. a scene-mate's: what that task's expert would do from here)."""
        self._ensure_env()
        expert = self._expert if task is None or task == self.task else scripted_expert(check_task(task))
        return np.asarray(expert.get_action(self._raw_obs), dtype=np.float32)

    def hand_and_object(self) -> tuple[np.ndarray, np.ndarray]:
        """The end effector's position and the scene's (first) object's, in metres: the handle a task moves."""
        return self._raw_obs[:3].copy(), self._raw_obs[4:7].copy()

    def close(self) -> None:
        if self._env is not None:
            self._viewer.make_context_current()
            self._env.close()
            self._env = None
            self._state_changed()


def observation_features(image_size: int) -> dict:
    return spec.observation_features(image_size, STATE_NAMES)


def action_feature() -> dict:
    return spec.action_feature(ACTION_NAMES)
