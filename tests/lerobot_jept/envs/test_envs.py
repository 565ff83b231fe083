"""What both simulator envs share: one camera image per simulator state."""

import numpy as np
import pytest

from lerobot_jept.envs.metaworld import JeptMetaworldEnv
from lerobot_jept.envs.robosuite import JeptRobosuiteEnv


@pytest.mark.parametrize(
    "make",
    [
        lambda: JeptMetaworldEnv("door-open-v3", image_size=32),
        lambda: JeptRobosuiteEnv("panda-lift", image_size=32),
    ],
)
def test_render_is_the_observation_drawn_once_per_state(make):
    env = make()
    draws = []
    draw = env._draw
    env._draw = lambda: draws.append(1) or draw()
    obs, _ = env.reset(seed=3)
    images = [obs["pixels"]]
    for _ in range(4):
        # LeRobot's eval renders after every reset and step, for its videos: the same image, not a second draw.
        np.testing.assert_array_equal(env.render(), obs["pixels"])
        np.testing.assert_array_equal(draw(), obs["pixels"])  # exact: a fresh draw of this state
        env.render()[:] = 0  # a caller's copy, not the env's image
        np.testing.assert_array_equal(env.render(), obs["pixels"])
        obs, *_ = env.step(np.full(env.action_space.shape, 0.8, np.float32))
        images.append(obs["pixels"])
    assert len(draws) == 5  # one per state: the reset and four steps
    assert all((a != b).any() for a, b in zip(images, images[1:], strict=False))  # the arm moves
    env.reset(seed=3)
    np.testing.assert_array_equal(env.render(), images[0])  # a reset draws again
    env.close()


@pytest.mark.parametrize(
    "make",
    [
        lambda: JeptMetaworldEnv("door-open-v3", image_size=32),
        lambda: JeptRobosuiteEnv("panda-lift", image_size=32),
    ],
)
def test_without_images_nothing_is_drawn_and_the_states_are_the_same(make):
    """draw_images=False (the random floor): black images of the observation's shape, no draw, and the same
    self-states and successes as with images."""
    runs = []
    for draw_images in (True, False):
        env = make()
        env.draw_images = draw_images
        draws = []
        draw = env._draw
        env._draw = lambda draws=draws, draw=draw: draws.append(1) or draw()
        obs, _ = env.reset(seed=3)
        states, pixels = [obs["agent_pos"]], [obs["pixels"]]
        for _ in range(3):
            obs, _, success, *_ = env.step(np.full(env.action_space.shape, 0.8, np.float32))
            states.append(obs["agent_pos"])
            pixels.append(obs["pixels"])
        runs.append((states, pixels, len(draws), success))
        env.close()
    (states, pixels, draws, success), (states_off, pixels_off, draws_off, success_off) = runs
    assert draws == 4 and draws_off == 0
    assert all(
        p.shape == q.shape and p.dtype == q.dtype and not q.any()
        for p, q in zip(pixels, pixels_off, strict=True)
    )
    assert any(p.any() for p in pixels)
    np.testing.assert_array_equal(np.stack(states), np.stack(states_off))
    assert success == success_off


def test_envs_of_one_task_draw_mt1_goals_once(monkeypatch):
    import metaworld

    from lerobot_jept.envs import metaworld as mw

    calls = []
    real = metaworld.MT1
    monkeypatch.setattr(metaworld, "MT1", lambda *a, **k: calls.append(a) or real(*a, **k))
    mw._mt1_task.cache_clear()
    state = np.random.get_state()
    first, second = (JeptMetaworldEnv("window-close-v3", image_size=32) for _ in range(2))
    obs = [env.reset(seed=7)[0] for env in (first, second)]
    assert calls == [("window-close-v3",)]  # the second env reuses the first's goals
    np.testing.assert_array_equal(obs[0]["pixels"], obs[1]["pixels"])
    np.testing.assert_array_equal(obs[0]["agent_pos"], obs[1]["agent_pos"])
    assert np.random.get_state()[1].tolist() == state[1].tolist()  # numpy's global random state untouched
    for env in (first, second):
        env.close()
