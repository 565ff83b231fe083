"""A stand-in for an SO-100 arm, for LeRobot's real rollout loop: six position-controlled joints whose motors
are simulated (each joint moves to its commanded angle) and two cameras whose frames are drawn from the joint
angles. Registered as ``--robot.type=jept_standin_arm``; every command it receives is kept in ``SENT``."""

from dataclasses import dataclass, field

import numpy as np
from lerobot.robots.config import RobotConfig
from lerobot.robots.robot import Robot

JOINTS = ["shoulder_pan", "shoulder_lift", "elbow_flex", "wrist_flex", "wrist_roll", "gripper"]
CAMERAS = ("front", "wrist")
SENT: list[dict[str, float]] = []


@RobotConfig.register_subclass("jept_standin_arm")
@dataclass(kw_only=True)
class StandInArmConfig(RobotConfig):
    image_size: int = 32
    start: list[float] = field(default_factory=lambda: [0.0, 0.0, 0.0, 0.0, 0.0, 50.0])


class StandInArm(Robot):
    config_class = StandInArmConfig
    name = "jept_standin_arm"

    def __init__(self, config: StandInArmConfig):
        super().__init__(config)
        self.config = config
        self.joints = np.array(config.start, dtype=np.float32)
        self._connected = False

    @property
    def observation_features(self) -> dict:
        size = self.config.image_size
        return {**{f"{j}.pos": float for j in JOINTS}, **{c: (size, size, 3) for c in CAMERAS}}

    @property
    def action_features(self) -> dict:
        return {f"{j}.pos": float for j in JOINTS}

    @property
    def is_connected(self) -> bool:
        return self._connected

    def connect(self, calibrate: bool = True) -> None:
        self._connected = True

    @property
    def is_calibrated(self) -> bool:
        return True

    def calibrate(self) -> None:
        pass

    def configure(self) -> None:
        pass

    def get_observation(self) -> dict:
        size = self.config.image_size
        shade = np.clip(128 + self.joints, 0, 255).astype(np.uint8)
        frames = {
            camera: np.broadcast_to(shade[i : i + 3], (size, size, 3)).copy()
            for i, camera in enumerate(CAMERAS)
        }
        return {**{f"{j}.pos": float(a) for j, a in zip(JOINTS, self.joints, strict=True)}, **frames}

    def send_action(self, action: dict) -> dict:
        SENT.append({k: float(v) for k, v in action.items()})
        self.joints = np.array([action[f"{j}.pos"] for j in JOINTS], dtype=np.float32)
        return action

    def disconnect(self) -> None:
        self._connected = False
