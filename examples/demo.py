"""`make demo`: the main job end to end on a small embedded default.

Runs the real command-line entry points one after the other and prints each command first, so every step
can be re-run by hand:
1. `jept-build-metaworld`: a small Meta-World mixture into $HF_LEROBOT_HOME: window-close, door-open and
   faucet-open with actions (the demo tasks, 20 episodes each) and window-open as 60 expert videos only (the
   video-only task: the window's scene-mate, so only the prompt video says whether to open or close it), 64 px,
   the experts acting at random 15% of the time;
2. `lerobot-train --policy.type=jept` (examples/configs/train_jept_small_cpu.json, the default `plus` recipe) on
   the mix repo;
3. `jept-eval-suite`: LeRobot's eval of the video-only task, printed in the paper's Table 1 layout with the random
   7-bin policy's success on the same env seeds beside it (the floor). `--splits='[demo, video]'` on the printed
   command evaluates the demo tasks too.
Sizes come from the environment: JEPT_DEMO_STEPS (training steps), JEPT_DEMO_EPISODES (evaluation episodes).
"""

import os
import shlex
import shutil
import subprocess
import sys
import time

REPO_ID = "local/jept_demo_window_open"
OUTPUT = "outputs/demo"
STEPS = int(os.environ.get("JEPT_DEMO_STEPS", 600))
EPISODES = int(os.environ.get("JEPT_DEMO_EPISODES", 10))
IMAGE_SIZE = 64
BUILD = [
    "jept-build-metaworld",
    f"--repo_id={REPO_ID}",
    "--demo_tasks=[window-close-v3, door-open-v3, faucet-open-v3]",
    "--video_tasks=[window-open-v3]",
    "--unseen_tasks=[]",
    "--episodes_per_task=20",
    "--video_episodes_per_task=60",
    "--prompts_per_task=3",
    "--probe_episodes_per_task=2",
    f"--image_size={IMAGE_SIZE}",
    "--expert_random_prob=0.15",
    "--episodes_per_shard=10",
    "--num_workers=2",
]


def run(cmd: list[str]) -> None:
    print(f"\n$ {shlex.join(cmd)}", flush=True)
    start = time.perf_counter()
    subprocess.run([str(a) for a in cmd], check=True)
    print(f"({time.perf_counter() - start:.0f} s)", flush=True)


def main() -> None:
    bin_dir = f"{sys.prefix}/bin/"
    run([bin_dir + BUILD[0], *BUILD[1:]])
    print(f"\nDatasets ready: {REPO_ID}_demo, _video, _prompts, _mix (under $HF_LEROBOT_HOME).")
    train_dir = f"{OUTPUT}/train"
    shutil.rmtree(train_dir, ignore_errors=True)  # lerobot-train refuses an existing output dir
    run(
        [
            bin_dir + "lerobot-train",
            "--config_path=examples/configs/train_jept_small_cpu.json",
            f"--dataset.repo_id={REPO_ID}_mix",
            f"--policy.prompt_repo_id={REPO_ID}_prompts",
            f"--policy.image_size={IMAGE_SIZE}",
            f"--steps={STEPS}",
            f"--save_freq={STEPS}",
            f"--output_dir={train_dir}",
        ]
    )
    run(
        [
            bin_dir + "jept-eval-suite",
            f"--policy.path={train_dir}/checkpoints/last/pretrained_model",
            f"--dataset.repo_id={REPO_ID}_mix",
            "--splits=[video]",
            f"--n_episodes={EPISODES}",
            f"--batch_size={EPISODES}",
            f"--floor_episodes={EPISODES}",
            f"--output_dir={OUTPUT}/suite",
        ]
    )


if __name__ == "__main__":
    main()
