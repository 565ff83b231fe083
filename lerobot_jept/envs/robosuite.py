"""The one definition of a JEPT robosuite observation (paper, Section 4.3 and Appendix B.1).

A Panda arm executes every task; prompt videos show the same manipulation done by Panda, Sawyer, IIWA or UR5e.
Tasks are named ``<prompt arm>-<manipulation>`` (``sawyer-lift``: Panda lifts, prompted by a Sawyer video).
:class:`JeptRobosuiteEnv` renders the ``agentview`` camera at ``image_size`` (flipped upright) with the fast
settings (no MSAA, shadows or reflections) and reports the self-state of the executing arm; ``embodiment="prompt"``
makes the prompt arm execute instead (to record prompt videos).
"""

import atexit
import difflib
import xml.etree.ElementTree as ET

import numpy as np
from gymnasium import spaces

from lerobot_jept.envs import spec
from lerobot_jept.envs.rendering import import_simulator, setup_offscreen_gl
from lerobot_jept.envs.robosuite_experts import make_expert
from lerobot_jept.policies.discretization import snap_to_bins

ARMS = {"panda": "Panda", "sawyer": "Sawyer", "iiwa": "IIWA", "ur5e": "UR5e"}
MANIPULATIONS = {
    "lift": "Lift",
    "stack": "Stack",
    "can": "PickPlaceCan",
    "square": "NutAssemblySquare",
}  # robosuite env per manipulation with a scripted expert
EXECUTING_ARM = "panda"
ROBOT_TYPE = "panda"
CAMERA_NAME = "agentview"
CONTROL_FREQ = 20
ACTION_DIM = 7
ACTION_NAMES = ["dx", "dy", "dz", "droll", "dpitch", "dyaw", "gripper"]
NUM_JOINTS = 7  # Panda; arms with fewer joints (UR5e: 6) are zero-padded in prompt recordings
STATE_NAMES = (
    [f"joint_pos_{i}" for i in range(NUM_JOINTS)]
    + [f"joint_vel_{i}" for i in range(NUM_JOINTS)]
    + ["eef_x", "eef_y", "eef_z", "eef_qx", "eef_qy", "eef_qz", "eef_qw", "gripper_0", "gripper_1"]
)
STATE_DIM = len(STATE_NAMES)
# Contacts robosuite 1.5.2's models get wrong, per arm. The Sawyer's link 0 collision sphere rests on its base's
# collision cylinder, and the friction holds the base joint right_j0 still (it turns 0.004 rad under 16 Nm), so
# the arm reaches sideways only by contorting its wrist; robosuite removed the same contact from the Jaco (PR 235).
EXCLUDED_CONTACTS = {"Sawyer": [("robot0_right_arm_base_link", "robot0_right_l0")]}


def available_tasks() -> list[str]:
    return [f"{arm}-{m}" for m in MANIPULATIONS for arm in ARMS]


def check_task(task: str) -> str:
    if task not in available_tasks():
        close = difflib.get_close_matches(task, available_tasks(), n=3)
        hint = f" Did you mean {', '.join(close)}?" if close else ""
        raise ValueError(
            f"Unknown robosuite task {task!r}: tasks are <prompt arm>-<manipulation> with arms "
            f"{sorted(ARMS)} and manipulations {sorted(MANIPULATIONS)}.{hint}"
        )
    return task


def split_task(task: str) -> tuple[str, str]:
    arm, manipulation = check_task(task).split("-", 1)
    return arm, manipulation


def task_description(task: str) -> str:
    arm, manipulation = split_task(task)
    return f"{manipulation} (prompted by {ARMS[arm]})"


class JeptRobosuiteEnv(spec.OneImagePerState):
    """A robosuite task under the JEPT protocol: ``{"pixels", "agent_pos"}`` observations, 7-D OSC_POSE actions.

    Args:
        task: ``<prompt arm>-<manipulation>``, e.g. ``"sawyer-stack"``.
        image_size: side of the square ``agentview`` image.
        max_episode_steps: steps before truncation (the paper: 200).
        embodiment: ``"panda"`` (the executing arm, for demos, videos and evaluation) or ``"prompt"`` (the
            task's prompt arm, for recording prompt videos).
    """

    metadata = {"render_modes": ["rgb_array"], "render_fps": CONTROL_FREQ}

    def __init__(
        self, task: str, image_size: int = 224, max_episode_steps: int = 200, embodiment: str = "panda"
    ):
        super().__init__()
        self.task = check_task(task)
        self.prompt_arm, self.manipulation = split_task(task)
        self.task_description = task_description(task)
        self.arm = EXECUTING_ARM if embodiment == "panda" else self.prompt_arm
        self.image_size = image_size
        self._max_episode_steps = max_episode_steps
        self.render_mode = "rgb_array"
        self.observation_space = spec.observation_space(image_size, STATE_DIM)
        self.action_space = spaces.Box(-1.0, 1.0, (ACTION_DIM,), np.float32)
        self._env = None
        self._raw_obs = None
        self._expert = None
        self._steps = 0

    @property
    def fps(self) -> int:
        return CONTROL_FREQ

    def _ensure_env(self) -> None:
        if self._env is not None:
            return
        setup_offscreen_gl()
        robosuite = import_simulator("robosuite", "robosuite")
        controllers = import_simulator("robosuite.controllers", "robosuite")

        robot = ARMS[self.arm]
        self._env = robosuite.make(
            MANIPULATIONS[self.manipulation],
            robots=robot,
            controller_configs=controllers.load_composite_controller_config(robot=robot),
            has_renderer=False,
            has_offscreen_renderer=True,
            use_camera_obs=False,
            control_freq=CONTROL_FREQ,
            horizon=10_000,  # truncation is ours
            hard_reset=False,
            ignore_done=True,
            seed=0,
        )
        if robot in EXCLUDED_CONTACTS:
            self._env.reset_from_xml_string(
                excluding_contacts(self._env.model.get_xml(), EXCLUDED_CONTACTS[robot])
            )
        self._env.reset()
        self._fast_render()
        atexit.register(self.close)

    def _fast_render(self) -> None:
        """No MSAA, shadows or reflections: several times faster on Mesa's CPU renderer."""
        import mujoco

        ctx = self._env.sim._render_context_offscreen
        ctx.gl_ctx.make_current()
        self._env.sim.model._model.vis.quality.offsamples = 0
        ctx.con.free()
        ctx._set_mujoco_context_and_buffers()
        ctx.scn.flags[mujoco.mjtRndFlag.mjRND_SHADOW] = 0
        ctx.scn.flags[mujoco.mjtRndFlag.mjRND_REFLECTION] = 0

    def _draw(self) -> np.ndarray:
        self._env.sim._render_context_offscreen.gl_ctx.make_current()
        image = self._env.sim.render(width=self.image_size, height=self.image_size, camera_name=CAMERA_NAME)
        return np.ascontiguousarray(image[::-1])

    def _state(self) -> np.ndarray:
        o = self._raw_obs
        joints = np.zeros(2 * NUM_JOINTS, np.float32)
        n = len(o["robot0_joint_pos"])
        joints[:n], joints[NUM_JOINTS : NUM_JOINTS + n] = o["robot0_joint_pos"], o["robot0_joint_vel"]
        gripper = np.zeros(2, np.float32)
        gripper[: min(2, len(o["robot0_gripper_qpos"]))] = o["robot0_gripper_qpos"][:2]
        return np.concatenate([joints, o["robot0_eef_pos"], o["robot0_eef_quat"], gripper]).astype(np.float32)

    def _observation(self) -> dict:
        return {"pixels": self.observed_image(), "agent_pos": self._state()}

    def reset(self, seed: int | None = None, options: dict | None = None):
        self._ensure_env()
        super().reset(seed=seed)
        if seed is not None:  # object placement and the robot's initial noise, from this seed
            self._env.rng.bit_generator.state = np.random.default_rng(seed).bit_generator.state
            np.random.seed(seed)
        self._state_changed()
        self._raw_obs = self._env.reset()
        self._expert = make_expert(self.manipulation, self._env)
        self._steps = 0
        return self._observation(), {"is_success": False}

    def _advance(self, action: np.ndarray) -> tuple[float, bool, bool]:
        """One control step without rendering: reward, success, truncated."""
        self._ensure_env()
        action = spec.checked_action(action, ACTION_DIM)
        self._state_changed()
        self._raw_obs, reward, _, _ = self._env.step(action)
        success = bool(self._env._check_success())
        self._steps += 1
        return float(reward), success, self._steps >= self._max_episode_steps and not success

    def step(self, action: np.ndarray):
        reward, success, truncated = self._advance(action)
        info = {"is_success": success, "task": self.task}
        return self._observation(), reward, success, truncated, info

    def expert_succeeds(self, seed: int, num_bins: int = 7) -> bool:
        """Whether the scripted expert, its actions snapped to ``num_bins`` bins, succeeds in the episode a
        build would record from ``seed`` (same reset, steps and truncation; no frames are rendered)."""
        self.reset(seed=seed)
        while True:
            _, success, truncated = self._advance(snap_to_bins(self.expert_action(), num_bins))
            if success or truncated:
                return success

    def expert_action(self) -> np.ndarray:
        """The scripted expert's continuous action for the current state."""
        self._ensure_env()
        return self._expert(self._raw_obs).astype(np.float32)

    def close(self) -> None:
        if self._env is not None:
            self._env.sim._render_context_offscreen.gl_ctx.make_current()
            self._env.close()
            self._env = None
            self._state_changed()


def excluding_contacts(xml: str, body_pairs: list[tuple[str, str]]) -> str:
    """The MJCF ``xml`` with contacts between each pair of bodies turned off."""
    root = ET.fromstring(xml)
    contact = root.find("contact")
    if contact is None:
        contact = ET.SubElement(root, "contact")
    for body1, body2 in body_pairs:
        ET.SubElement(contact, "exclude", body1=body1, body2=body2)
    return ET.tostring(root, encoding="unicode")


def observation_features(image_size: int) -> dict:
    return spec.observation_features(image_size, STATE_NAMES)


def action_feature() -> dict:
    return spec.action_feature(ACTION_NAMES)
