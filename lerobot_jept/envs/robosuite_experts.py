"""Scripted, state-based experts for robosuite tasks (robosuite ships none), for any of the four arms.

They read privileged object poses and emit OSC_POSE actions (dx, dy, dz, droll, dpitch, dyaw, gripper) in
[-1, 1], designed to keep working once every dimension is snapped to 7 bins: gains are doubled so that a
residual error larger than the dead zone of the middle bin still moves the arm, and every phase has a way out
(blocked descents grasp where they are, a dropped object restarts the approach).
"""

import numpy as np

POS_SCALE = 0.05  # OSC_POSE: an action of 1 moves the end effector target 5 cm
ROT_SCALE = 0.5  # ... or rotates it 0.5 rad
GAIN = 2.0
OPEN, CLOSE = -1.0, 1.0


def quat2mat(quat_xyzw: np.ndarray) -> np.ndarray:
    """robosuite's rotation matrix of an (x, y, z, w) quaternion (imported when an expert first runs)."""
    from robosuite.utils.transform_utils import quat2mat as robosuite_quat2mat

    return robosuite_quat2mat(quat_xyzw)


def yaw_of(quat_xyzw: np.ndarray) -> float:
    m = quat2mat(quat_xyzw)
    return float(np.arctan2(m[1, 0], m[0, 0]))


def wrap(angle: float, period: float) -> float:
    """``angle`` into [-period / 2, period / 2)."""
    return (angle + period / 2) % period - period / 2


def osc_action(
    eef: np.ndarray, goal: np.ndarray, turn: float | np.ndarray, gripper: float, gain: float = GAIN
) -> np.ndarray:
    """Move towards ``goal`` and rotate by ``turn`` (a yaw error, or a (roll, pitch, yaw) rotation vector)."""
    move = gain * (goal - eef) / POS_SCALE
    rotation = np.array([0.0, 0.0, turn]) if np.isscalar(turn) else np.asarray(turn)
    return np.clip(np.concatenate([move, GAIN * rotation / ROT_SCALE, [gripper]]), -1.0, 1.0)


class GraspingExpert:
    """What the experts share: the phase clock and the grasp. Phases 0-2 go above the grasp point (yaw
    matched), down to it, and close; a drop in phases 3-5 starts again, and a descent blocked for 25 steps grasps
    where it is."""

    approach_height = 0.10  # above the grasp point before descending
    descend_tolerance = 0.008  # how close in height the descent must get
    centre_tolerance = None  # if set, the descent pauses while the grasp point is further off than this in xy

    def __init__(self):
        self.phase, self.steps_in_phase, self._last = 0, 0, None

    def tick(self, dropped: bool) -> bool:
        """Advance the phase clock for one step; True when a drop restarted the approach."""
        restarted = self.phase in (3, 4, 5) and dropped
        if restarted:
            self.phase = 0
        if self.phase == self._last == 1 and self.steps_in_phase >= 25:  # blocked on the way down: grasp here
            self.phase = 2
        if self._last != self.phase:
            self._last, self.steps_in_phase = self.phase, 0
        self.steps_in_phase += 1
        return restarted

    def grasp(self, eef: np.ndarray, at: np.ndarray, yaw_error: float) -> tuple | None:
        """``(goal, gripper, yaw turn)`` in phases 0-2, None after them."""
        if self.phase == 0:
            goal = at + [0, 0, self.approach_height]
            if np.linalg.norm(goal - eef) < 0.01 and abs(yaw_error) < 0.08:
                self.phase = 1
            return goal, OPEN, yaw_error
        if self.phase == 1:
            if abs(eef[2] - at[2]) < self.descend_tolerance:
                self.phase = 2
            goal = at.copy()
            if self.centre_tolerance is not None and np.abs(at[:2] - eef[:2]).max() > self.centre_tolerance:
                goal[2] = eef[2]
            return goal, OPEN, yaw_error
        if self.phase == 2:
            if self.steps_in_phase > 10:
                self.phase = 3
            return at.copy(), CLOSE, 0.0
        return None


class PickPlaceExpert(GraspingExpert):
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
        place_tolerance: float = 0.009,
        centre_tolerance: float | None = None,
        carry_while_lifting: bool = False,
    ):
        super().__init__()
        self.centre_tolerance, self.carry_while_lifting = centre_tolerance, carry_while_lifting
        self.obj, self.target, self.place_height, self.yaw_symmetry = obj, target, place_height, yaw_symmetry
        self.carry_height, self.place_tolerance = carry_height, place_tolerance
        self.round_yaw = None

    def target_pos(self, obs: dict) -> np.ndarray:
        return obs[f"{self.target}_pos"] if isinstance(self.target, str) else np.asarray(self.target)

    def __call__(self, obs: dict) -> np.ndarray:
        eef, p = obs["robot0_eef_pos"], obs[f"{self.obj}_pos"]
        self.tick(dropped=np.linalg.norm(p - eef) > 0.04)
        eef_yaw = yaw_of(obs["robot0_eef_quat"])
        if self.yaw_symmetry is not None:
            yaw_error = wrap(yaw_of(obs[f"{self.obj}_quat"]) - eef_yaw, self.yaw_symmetry)
        else:  # a round object. The fingers start closing along y; turned by the approach's heading, they close
            # across the way the arm comes, and it arrives a few mm short: no finger lands on the object's rim
            if self.round_yaw is None:
                self.round_yaw = eef_yaw + np.arctan2(*(p - eef)[1::-1])
            yaw_error = wrap(self.round_yaw - eef_yaw, np.pi)
        goal, gripper, turn = eef.copy(), OPEN, 0.0
        grasping = self.grasp(eef, p, yaw_error)
        if grasping is not None:
            goal, gripper, turn = grasping
        elif self.phase == 3:
            gripper = CLOSE
            if self.target is None:
                goal = np.array([eef[0], eef[1], p[2] + 0.15])
            else:
                t = self.target_pos(obs)
                goal = np.array([eef[0], eef[1], t[2] + self.carry_height])
                if self.carry_while_lifting:  # diagonally: as far sideways as up, clear of walls a bin away
                    goal[:2] = t[:2] + eef[:2] - p[:2]
                if abs(goal[2] - eef[2]) < 0.01:
                    self.phase = 4
        elif self.phase == 4:
            gripper, t = CLOSE, self.target_pos(obs)
            goal = np.array([t[0] + eef[0] - p[0], t[1] + eef[1] - p[1], t[2] + self.carry_height])
            if np.linalg.norm(goal[:2] - eef[:2]) < self.place_tolerance:
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


# Gain and integral gain of the square nut's final alignment, per arm, chosen on seeded samples: the UR5e tracks
# its target tightly; the others settle a few millimetres short of it, which the integral term removes.
SQUARE_GAINS = {"Panda": (3.0, 0.1), "Sawyer": (3.0, 0.1), "IIWA": (3.0, 0.1), "UR5e": (2.0, 0.0)}
# Where the nut's handle may point once it is on the peg, in quarter turns from +x (k = 0, the far side, is out of
# every arm's reach). The IIWA, with its long Robotiq gripper, holds the nut over the peg at full extension unless
# the handle points back at it: with the handle sideways its elbow straightens and it stalls short of the peg.
SQUARE_HANDLE_DIRECTIONS = {"IIWA": (2,)}
SLIDE = 0.008  # m the fingers may slide down the handle while the nut is lowered onto the peg
WRIST_MARGIN = 0.2  # rad the last joint should keep from its limits after the nut is turned


class SquareExpert(GraspingExpert):
    """NutAssemblySquare: grasp the nut across its handle, lift it, carry it level over the square peg with its
    hole centred and its handle turned away from the far side (towards the robot or sideways, so every arm stays
    in reach), lower it until the peg is inside the hole, let go and retreat.

    The nut hangs from its handle and swings, so the alignment waits until the hole is within ``tolerance`` of
    the peg (the clearance is 6.75 mm) and the nut is level, with an integral term for arms that settle short
    of the target; a descent that jams (or lets the fingers slide down the handle) goes back to realigning.
    An arm allowed one handle direction may have to turn the nut up to half a circle: it turns the way round
    that keeps its last joint in range.
    """

    approach_height = 0.08
    descend_tolerance = 0.006

    def __init__(self, env, tolerance: float = 0.006, tilt_tolerance: float = 0.08, engage: float = 0.015):
        self.env, self.tolerance, self.tilt_tolerance, self.engage = env, tolerance, tilt_tolerance, engage
        robot = env.robots[0]
        self.gain, self.integral_gain = SQUARE_GAINS.get(robot.name, (GAIN, 0.0))
        self.handle_directions = SQUARE_HANDLE_DIRECTIONS.get(robot.name, (1, 2, 3))
        super().__init__()
        self.handle = env.sim.model.site_name2id(env.nuts[0].important_sites["handle"])
        self.wrist = env.sim.model.joint_name2id(robot.robot_joints[-1])
        self.start_yaw, self.turn_left, self.last_nut_yaw, self.integral = None, None, None, np.zeros(2)
        self.grip_height = 0.0

    def turn_to_peg(self, nut_yaw: float, eef_yaw: float) -> float:
        """The nut's yaw change still to go to line its sides up with the peg's, its handle in one of the arm's
        ``handle_directions``, leaving the gripper closest to its starting yaw (away from the wrist's joint
        limits). The choice is kept until the nut is dropped: two equally good ones would otherwise alternate."""
        if self.turn_left is None:
            turns = [wrap(k * np.pi / 2 - nut_yaw, 2 * np.pi) for k in self.handle_directions]
            turn = min(turns, key=lambda turn: abs(wrap(eef_yaw + turn - self.start_yaw, 2 * np.pi)))
            other_way = turn - np.sign(turn) * 2 * np.pi  # one direction: up to half a turn, either way round
            if len(turns) == 1 and self.wrist_room(turn) < min(WRIST_MARGIN, self.wrist_room(other_way)):
                turn = other_way
            self.turn_left, self.last_nut_yaw = turn, nut_yaw
        self.turn_left -= wrap(nut_yaw - self.last_nut_yaw, 2 * np.pi)
        self.last_nut_yaw = nut_yaw
        return self.turn_left

    def wrist_room(self, turn: float) -> float:
        """How far (rad) the last joint (its axis along the gripper's, vertical) ends from its nearer limit once
        the gripper has turned by ``turn`` about the vertical; negative: beyond it."""
        model, data = self.env.sim.model, self.env.sim.data
        low, high = model.jnt_range[self.wrist]
        end = data.qpos[model.jnt_qposadr[self.wrist]] + turn * np.sign(data.xaxis[self.wrist][2])
        return min(end - low, high - end)

    @staticmethod
    def levelling(nut_quat: np.ndarray) -> np.ndarray:
        """The (roll, pitch) rotation that brings the nut's axis back to vertical."""
        z = quat2mat(nut_quat)[:, 2]
        axis = np.cross(z, [0.0, 0.0, 1.0])
        norm = np.linalg.norm(axis)
        return axis[:2] / norm * np.arccos(np.clip(z[2], -1.0, 1.0)) if norm > 1e-6 else np.zeros(2)

    def __call__(self, obs: dict) -> np.ndarray:
        env = self.env
        eef, centre, nut_quat = obs["robot0_eef_pos"], obs["SquareNut_pos"], obs["SquareNut_quat"]
        grasp = env.sim.data.site_xpos[self.handle].copy()  # the middle of the handle
        peg = env.sim.data.body_xpos[env.peg1_body_id]
        peg_top = peg[2] + 0.1
        nut_yaw, eef_yaw = yaw_of(nut_quat), yaw_of(obs["robot0_eef_quat"])
        if self.start_yaw is None:
            self.start_yaw = eef_yaw
        if self.tick(dropped=np.linalg.norm(grasp - eef) > 0.05):
            self.turn_left = None
        goal, gripper, turn = eef.copy(), OPEN, np.zeros(3)
        grasping = self.grasp(eef, grasp, wrap(nut_yaw - eef_yaw, np.pi))  # fingers close across the handle
        if grasping is not None:
            goal, gripper, turn[2] = grasping
        elif self.phase == 3:
            goal, gripper = np.array([eef[0], eef[1], peg_top + 0.08]), CLOSE
            if abs(goal[2] - eef[2]) < 0.01:
                self.phase = 4
        elif self.phase in (4, 5):
            gripper = CLOSE
            turn[:2], turn[2] = self.levelling(nut_quat), self.turn_to_peg(nut_yaw, eef_yaw)
            over_peg = peg[:2] + eef[:2] - centre[:2]
            if self.phase == 4:  # the nut's bottom 2 cm above the peg top
                goal = np.array([*over_peg, peg_top + 0.03 + eef[2] - centre[2]])
                if (
                    np.abs(centre[:2] - peg[:2]).max() < self.tolerance
                    and np.linalg.norm(turn[:2]) < self.tilt_tolerance
                    and abs(turn[2]) < 0.1
                    and abs(goal[2] - eef[2]) < 0.01
                ):
                    self.phase, self.grip_height = 5, eef[2] - centre[2]
            else:  # lower it, still centred and level
                goal = np.array([*over_peg, eef[2] - 0.01])
                if centre[2] < peg_top - self.engage:
                    self.phase = 6
                elif self.steps_in_phase > 40 or eef[2] - centre[2] < self.grip_height - SLIDE:
                    self.phase = 4  # jammed (or the fingers slide down the handle of a nut stuck on the peg)
            error = goal[:2] - eef[:2]
            if np.abs(error).max() < 0.02:
                self.integral = np.clip(self.integral + self.integral_gain * error, -0.02, 0.02)
            goal[:2] += self.integral
        else:
            goal = eef + [0, 0, 0.0 if self.steps_in_phase < 8 else 0.03]
        if self.phase not in (4, 5):
            self.integral = np.zeros(2)
        return osc_action(eef, goal, turn, gripper, self.gain)


def make_expert(manipulation: str, env=None):
    """A fresh expert for one episode of ``manipulation`` (``env``: the robosuite env, for fixed targets)."""
    if manipulation == "lift":
        return PickPlaceExpert("cube")
    if manipulation == "stack":
        return PickPlaceExpert("cubeA", target="cubeB")
    if manipulation == "can":
        # anywhere in the can's quarter of the goal bin counts (robosuite's target placement is its centre): aim
        # for its point nearest the can, 5 cm inside
        centre, quarter = env.target_bin_placements[env.object_id], env.bin_size[:2] / 4
        start = env.sim.data.body_xpos[env.obj_body_id["Can"]][:2]
        target = [*np.clip(start, centre[:2] - quarter + 0.05, centre[:2] + quarter - 0.05), centre[2]]
        return PickPlaceExpert(
            "Can",
            target=np.array(target),
            place_height=0.12,
            yaw_symmetry=None,
            carry_height=0.18,
            place_tolerance=0.02,
            centre_tolerance=0.006,
            carry_while_lifting=True,
        )
    if manipulation == "square":
        return SquareExpert(env)
    raise ValueError(f"No scripted expert for {manipulation!r} yet.")
