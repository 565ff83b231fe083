"""`make demo`: the main job end to end on a small embedded default.

Runs the real command-line entry points one after the other and prints each command first, so every step
can be re-run by hand. Step 1 builds a tiny Meta-World mixture (2 demo tasks, 1 video-only task, 1 unseen
task) into $HF_LEROBOT_HOME.
"""

import shlex
import subprocess
import sys
import time

REPO_ID = "local/jept_demo"
BUILD = [
    "jept-build-metaworld",
    f"--repo_id={REPO_ID}",
    "--demo_tasks=[button-press-v3, reach-v3]",
    "--video_tasks=[drawer-close-v3]",
    "--unseen_tasks=[handle-press-v3]",
    "--episodes_per_task=10",
    "--prompts_per_task=3",
    "--image_size=96",
    "--episodes_per_shard=5",
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


if __name__ == "__main__":
    main()
