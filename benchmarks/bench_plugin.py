"""What installing the plugin costs every LeRobot command, each figure a ratio measured in the same run.

LeRobot imports every installed ``lerobot_policy_*`` distribution at the start of each command, so the plugin's
import is paid by ``lerobot-train`` and ``lerobot-calibrate`` alike. Each import is timed inside a fresh
process (interpreter start-up excluded), alternating the two sides, median of ``--repeats``.

- ``plugin_import_vs_lerobot``: ``import lerobot_policy_jept`` / ``import lerobot``. Goal <= 1.2.
- ``train_imports_with_plugin_vs_without``: ``import lerobot.scripts.lerobot_train`` followed by the plugin's
  import and registration (what ``lerobot-train`` does before parsing its flags) / the same without the plugin.
  No goal: the share of a training command's start-up that the policy types' registration takes.
"""

import argparse
import statistics
import subprocess
import sys

TIMED = "import time\nt = time.perf_counter()\n{code}\nprint(time.perf_counter() - t)\n"
SIDES = {
    "plugin_import_vs_lerobot": ("import lerobot_policy_jept", "import lerobot"),
    "train_imports_with_plugin_vs_without": (
        "import lerobot.scripts.lerobot_train\n"
        "from lerobot.utils.import_utils import register_third_party_plugins\n"
        "register_third_party_plugins()",
        "import lerobot.scripts.lerobot_train",
    ),
}


def import_seconds(code: str) -> float:
    proc = subprocess.run(
        [sys.executable, "-c", TIMED.format(code=code)], capture_output=True, text=True, check=True
    )
    return float(proc.stdout.strip().splitlines()[-1])


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeats", type=int, default=5)
    args = parser.parse_args()
    for name, (measured, baseline) in SIDES.items():
        import_seconds(measured), import_seconds(baseline)  # warm the file cache
        times = {"measured": [], "baseline": []}
        for _ in range(args.repeats):
            times["measured"].append(import_seconds(measured))
            times["baseline"].append(import_seconds(baseline))
        measured_s, baseline_s = statistics.median(times["measured"]), statistics.median(times["baseline"])
        print(f"{name}_s: {measured_s:.3f} vs {baseline_s:.3f}")
        print(f"{name}: {measured_s / baseline_s:.2f}")


if __name__ == "__main__":
    main()
