"""What every JEPT env shares: the observation space and the LeRobot features the builders write for it."""

from abc import ABC, abstractmethod

import gymnasium as gym
import numpy as np
from gymnasium import spaces


class OneImagePerState(gym.Env, ABC):
    """A simulator env whose camera image is drawn once per state.

    The observation and a later ``render`` (LeRobot's eval draws every step again for its videos) share one
    image, which halves the rendering of an evaluated rollout. Subclasses draw in ``_draw``, call
    ``_state_changed`` whenever the simulator's state may change (reset, step, close) and put
    :meth:`observed_image` in their observations.

    ``draw_images = False`` is for a caller that reads only the self-state and the success (the random floor):
    the observation's image is then black and never drawn, which skips most of a step's cost (rendering the
    scene on a CPU takes about ten times the physics of a Meta-World step).
    """

    _image: np.ndarray | None = None
    draw_images: bool = True

    @abstractmethod
    def _ensure_env(self) -> None:
        """Create the simulator (and its GL context) on first use."""

    @abstractmethod
    def _draw(self) -> np.ndarray:
        """Render the current state's camera image, upright, (H, W, 3) uint8."""

    def _state_changed(self) -> None:
        self._image = None

    def observed_image(self) -> np.ndarray:
        """The observation's camera image: :meth:`render`, or black with ``draw_images = False``."""
        if self.draw_images:
            return self.render()
        size = self.observation_space["pixels"].shape
        return np.zeros(size, np.uint8)

    def render(self) -> np.ndarray:
        """The camera image of the current state, upright, (H, W, 3) uint8."""
        self._ensure_env()
        if self._image is None:
            self._image = self._draw()
        return self._image.copy()


def observation_space(image_size: int, state_dim: int) -> spaces.Dict:
    """``{"pixels": (H, W, 3) uint8, "agent_pos": (state_dim,) float32}``."""
    return spaces.Dict(
        {
            "pixels": spaces.Box(0, 255, (image_size, image_size, 3), np.uint8),
            "agent_pos": spaces.Box(-np.inf, np.inf, (state_dim,), np.float32),
        }
    )


def checked_action(action, action_dim: int) -> np.ndarray:
    action = np.asarray(action, dtype=np.float32)
    if action.shape != (action_dim,):
        raise ValueError(f"Expected one action of shape ({action_dim},), got {action.shape}.")
    return action


def observation_features(image_size: int, state_names: list[str]) -> dict:
    """LeRobot dataset features of one observation (the builder writes them; the env produces them)."""
    return {
        "observation.image": {
            "dtype": "video",
            "shape": (image_size, image_size, 3),
            "names": ["height", "width", "channels"],
        },
        "observation.state": {"dtype": "float32", "shape": (len(state_names),), "names": list(state_names)},
    }


def action_feature(action_names: list[str]) -> dict:
    return {"dtype": "float32", "shape": (len(action_names),), "names": list(action_names)}


# Per-frame marker of a real action in mixes of demos and action-free videos (see lerobot_jept.datasets.mixing).
ACTION_LABELLED = "observation.action_labelled"


def action_labelled_feature() -> dict:
    return {"dtype": "float32", "shape": (1,), "names": ["labelled"]}
