"""What a prompt video costs each step of ``lerobot-eval``, a ratio measured in the same run.

- ``eval_step_with_prompt_vs_without``: one control step of ``lerobot-eval``'s observation path (the
  ``jept_metaworld`` vector env's step, LeRobot's ``preprocess_observation``, the env's processors and the
  policy's preprocessor, up to the policy's input) with the env showing a prompt video of the paper's size (250
  frames at 224 px) / the same without a prompt; median over ``--repeats`` steps after the episode's first,
  which carries the prompt. Goal <= 1.1: the prompt crosses from the env to the policy once per episode.
"""

import argparse
import os
import statistics
import tempfile
import time
from pathlib import Path

os.environ.setdefault("HF_HUB_OFFLINE", "1")
os.environ.setdefault("MUJOCO_GL", "egl")
os.environ.setdefault("HF_LEROBOT_HOME", tempfile.mkdtemp(prefix="jept_bench_home_"))

import numpy as np  # noqa: E402

TASK = "handle-press-v3"
FRAMES, SIZE = 250, 224


def write_prompt_bank(description: str) -> str:
    """A 250-frame 224 px prompt bank from a synthetic clip, through jept-prompts."""
    import av

    from lerobot_jept.datasets.prompt_videos import PromptVideosConfig, make_prompt_bank

    clip = Path(tempfile.mkdtemp(prefix="jept_bench_clip_")) / "clip.mp4"
    rng = np.random.default_rng(0)
    with av.open(str(clip), "w") as container:
        stream = container.add_stream("mpeg4", rate=20)
        stream.height = stream.width = SIZE
        stream.pix_fmt = "yuv420p"
        for _ in range(FRAMES):
            frame = rng.integers(0, 256, (SIZE, SIZE, 3), dtype=np.uint8)
            container.mux(stream.encode(av.VideoFrame.from_ndarray(frame, format="rgb24")))
        container.mux(stream.encode())
    repo = "bench/eval_prompts"
    make_prompt_bank(
        PromptVideosConfig(videos=str(clip), task=description, output_repo_id=repo, fps=20, image_size=SIZE)
    )
    return repo


def step_seconds(prompt_repo_id: str | None, repeats: int) -> float:
    import torch
    from lerobot.envs.utils import env_to_policy_features, preprocess_observation
    from lerobot.policies.factory import make_pre_post_processors

    from lerobot_jept import JEPTConfig, JeptMetaworldEnvConfig

    env_cfg = JeptMetaworldEnvConfig(
        task=TASK,
        image_size=SIZE,
        prompt_repo_id=prompt_repo_id,
        prompt_max_frames=FRAMES,
        episode_length=10_000,
    )
    policy_cfg = JEPTConfig(
        device="cpu", image_size=SIZE, max_prompt_length=FRAMES, prompt_repo_id=prompt_repo_id
    )
    features = env_to_policy_features(env_cfg)
    policy_cfg.input_features = {k: v for k, v in features.items() if k != "action"}
    policy_cfg.output_features = {"action": features["action"]}
    env_pre, _ = env_cfg.get_env_processors()
    pre, _ = make_pre_post_processors(policy_cfg, dataset_stats=None)
    env = env_cfg.create_envs(n_envs=1)[TASK][0]
    description = env.call("task_description")[0]
    action = np.zeros((1, env_cfg.ACTION_DIM), np.float32)

    def control_step(obs) -> dict:
        batch = preprocess_observation(obs)
        batch["task"] = [description]
        return pre(env_pre(batch))

    with torch.no_grad():
        obs, _ = env.reset(seed=0)
        first = control_step(obs)
        times = []
        for _ in range(repeats + 2):
            start = time.perf_counter()
            obs, *_ = env.step(action)
            control_step(obs)
            times.append(time.perf_counter() - start)
    env.close()
    assert prompt_repo_id is None or first["observation.prompt_video"].shape[1] == FRAMES
    return statistics.median(times[2:])


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeats", type=int, default=20)
    args = parser.parse_args()
    from lerobot_jept.envs.metaworld import task_description

    repo = write_prompt_bank(task_description(TASK))
    without = step_seconds(None, args.repeats)
    with_prompt = step_seconds(repo, args.repeats)
    print(f"eval_step_with_prompt_s: {with_prompt:.4f}")
    print(f"eval_step_without_prompt_s: {without:.4f}")
    print(f"eval_step_with_prompt_vs_without: {with_prompt / without:.2f}")


if __name__ == "__main__":
    main()
