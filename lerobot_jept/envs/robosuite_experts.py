"""Scripted, state-based experts for robosuite tasks (robosuite ships none), for any of the four arms.

They read privileged object poses and emit OSC_POSE actions (dx, dy, dz, droll, dpitch, dyaw, gripper) in
[-1, 1], designed to keep working once every dimension is snapped to 7 bins: gains are doubled so that a
residual error larger than the dead zone of the middle bin still moves the arm, and every phase has a way out
(blocked descents grasp where they are, a dropped object restarts the approach).
"""

import numpy as np
from robosuite.utils.transform_utils import quat2mat

POS_SCALE = 0.05  # OSC_POSE: an action of 1 moves the end effector target 5 cm
ROT_SCALE = 0.5  # ... or rotates it 0.5 rad
GAIN = 2.0
OPEN, CLOSE = -1.0, 1.0


def yaw_of(quat_xyzw: np.ndarray) -> float:
    m = quat2mat(quat_xyzw)
    return float(np.arctan2(m[1, 0], m[0, 0]))


def wrap(angle: float, period: float) -> float:
    """``angle`` into [-period / 2, period / 2)."""
    return (angle + period / 2) % period - period / 2


def osc_action(eef: np.ndarray, goal: np.ndarray, yaw_error: float, gripper: float) -> np.ndarray:
    move = GAIN * (goal - eef) / POS_SCALE
    turn = np.array([0.0, 0.0, GAIN * yaw_error / ROT_SCALE])
    return np.clip(np.concatenate([move, turn, [gripper]]), -1.0, 1.0)


class PickPlaceExpert:
    """Above the object (yaw matched up to ``yaw_symmetry``) -> descend -> close -> lift; with a ``target`` (an
    object name, or a fixed position), carry it above the target, lower it until it is ``place_height`` above,
    open and retreat."""

    def __init__(
        self,
        obj: str,
        target: str | np.ndarray | None = None,
        place_height: float = 0.045,
        yaw_symmetry: float | None = np.pi / 2,
        carry_height: float = 0.12,
    ):
        self.obj, self.target, self.place_height, self.yaw_symmetry = obj, target, place_height, yaw_symmetry
        self.carry_height = carry_height
        self.phase, self.steps_in_phase, self._last = 0, 0, None

    def target_pos(self, obs: dict) -> np.ndarray:
        return obs[f"{self.target}_pos"] if isinstance(self.target, str) else np.asarray(self.target)

    def __call__(self, obs: dict) -> np.ndarray:
        eef, p = obs["robot0_eef_pos"], obs[f"{self.obj}_pos"]
        if self._last != self.phase:
            self._last, self.steps_in_phase = self.phase, 0
        self.steps_in_phase += 1
        if self.phase in (3, 4, 5) and np.linalg.norm(p - eef) > 0.04:  # dropped: start again
            self.phase = 0
        if self.phase == 1 and self.steps_in_phase > 25:  # blocked on the way down: grasp here
            self.phase = 2
        yaw_error = 0.0
        if self.yaw_symmetry is not None:
            yaw_error = wrap(
                yaw_of(obs[f"{self.obj}_quat"]) - yaw_of(obs["robot0_eef_quat"]), self.yaw_symmetry
            )
        goal, gripper, turn = eef.copy(), OPEN, 0.0
        if self.phase == 0:
            goal, turn = p + [0, 0, 0.10], yaw_error
            if np.linalg.norm(goal - eef) < 0.01 and abs(yaw_error) < 0.08:
                self.phase = 1
        elif self.phase == 1:
            goal, turn = p.copy(), yaw_error
            if abs(eef[2] - goal[2]) < 0.008:
                self.phase = 2
        elif self.phase == 2:
            goal, gripper = p.copy(), CLOSE
            if self.steps_in_phase > 10:
                self.phase = 3
        elif self.phase == 3:
            gripper = CLOSE
            if self.target is None:
                goal = np.array([eef[0], eef[1], p[2] + 0.15])
            else:
                goal = np.array([eef[0], eef[1], self.target_pos(obs)[2] + self.carry_height])
                if abs(goal[2] - eef[2]) < 0.01:
                    self.phase = 4
        elif self.phase == 4:
            gripper, t = CLOSE, self.target_pos(obs)
            goal = np.array([t[0] + eef[0] - p[0], t[1] + eef[1] - p[1], t[2] + self.carry_height])
            if np.linalg.norm(goal[:2] - eef[:2]) < 0.009:
                self.phase = 5
        elif self.phase == 5:
            gripper, t = CLOSE, self.target_pos(obs)
            goal = np.array(
                [t[0] + eef[0] - p[0], t[1] + eef[1] - p[1], eef[2] - (p[2] - t[2] - self.place_height)]
            )
            if p[2] - t[2] < self.place_height + 0.01:
                self.phase = 6
        else:
            goal = eef + [0, 0, 0.0 if self.steps_in_phase < 5 else 0.05]
        return osc_action(eef, goal, turn, gripper)


def make_expert(manipulation: str, env=None):
    """A fresh expert for one episode of ``manipulation`` (``env``: the robosuite env, for fixed targets)."""
    if manipulation == "lift":
        return PickPlaceExpert("cube")
    if manipulation == "stack":
        return PickPlaceExpert("cubeA", target="cubeB")
    if manipulation == "can":
        bin_centre = env.target_bin_placements[env.object_to_id["can"]]
        return PickPlaceExpert(
            "Can", target=bin_centre, place_height=0.12, yaw_symmetry=None, carry_height=0.18
        )
    raise ValueError(f"No scripted expert for {manipulation!r} yet.")
