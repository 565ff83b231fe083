"""The action target over training seeds: two arms' ``jept-prompt-probe`` outputs side by side, per task.

    python -m examples.measurements.probe_seeds --arms='{videos: [RUN1/probe, RUN2/probe, RUN3/probe], demos: [...]}' \\
        --task=window-close-v3

Each folder (or JSON file) is one training seed's probe on the same held-out repo: a ``jept-prompt-probe``
output, or a ``jept-eval-suite`` output (its ``results.json`` carries the probe; a ``jept-study`` run's ``suite``
folder). For ``--task`` and for its split (T_demo / T_vid / T_unseen) this prints, per arm, the mean, the 95%
Student's t interval over seeds and the per-seed values of the probe's measures, then the target:
is the first arm's mean ``control`` whole-action accuracy on the task above the second arm's by more than the
spread over seeds (the larger of the two arms' ranges, max - min)? Beside it, Welch's t-test of the same
difference (its 95% interval and two-sided p), which does not grow stricter as seeds are added the way a range
does. Used throughout docs/results.md.
"""

import json
from dataclasses import dataclass, field
from pathlib import Path

import draccus
import numpy as np
from scipy import stats

from lerobot_jept.study.report import probe_fmt, probe_interval

TASK_MEASURES = (
    ("control_whole", "control whole (%)"),
    ("control_per_dim", "control per dim (%)"),
    ("inverse_whole", "inverse whole (%)"),
    ("swap_changed", "scene-mate's prompt changes the action (%)"),
    ("swap_control_whole", "control whole under the scene-mate's prompt (%)"),
    ("loss_obs", "L_obs"),
)
SPLIT_MEASURES = (
    ("control_whole", "control whole (%)"),
    ("inverse_whole", "inverse whole (%)"),
    ("swap_changed", "prompt swap changes the action (%)"),
    ("nc_accuracy_trained", "E_prt NC, trained tasks (%)"),
    ("loss_obs", "L_obs"),
)


@dataclass
class ProbeSeedsConfig:
    # arm name -> jept-prompt-probe / jept-eval-suite output folders (or their JSON files), one per training seed
    arms: dict[str, list[str]] = field(default_factory=dict)
    task: str = "window-close-v3"  # the task whose actions the target is about (a task of the probe repo)


def load_probe(path: str) -> dict:
    file = Path(path)
    if file.is_dir():
        file = next((file / n for n in ("prompt_probe.json", "results.json") if (file / n).is_file()), file)
    if not file.is_file():
        raise SystemExit(
            f"{file}: no prompt_probe.json or results.json: pass jept-prompt-probe's or jept-eval-suite's "
            "--output_dir."
        )
    probe = json.loads(file.read_text())
    if "actions" not in probe:  # a jept-eval-suite results.json: the probe is one of its entries
        if "actions" not in (probe.get("prompt_probe") or {}):
            raise SystemExit(
                f"{file} has no probe: run jept-eval-suite with --heldout_repo_id=ORG/NAME_probe."
            )
        probe = probe["prompt_probe"]
    return probe


def task_value(probe: dict, task: str, measure: str) -> float:
    """One measure of one task; a per-scene-mate measure is averaged over the task's scene-mates."""
    value = probe["actions"][task].get(measure, np.nan)
    if isinstance(value, dict):
        return float(np.mean(list(value.values()))) if value else np.nan
    return float(value)


def trained_nc(probe: dict) -> float:
    """E_prt nearest-centroid accuracy over the held-out prompts of every task the policy trained on."""
    trained = probe.get("prompt_separability", {}).get("trained_tasks") or {}
    return float(trained.get("nearest_centroid_accuracy", np.nan))


def split_of(probe: dict, task: str) -> str:
    return next(name for name, row in probe["splits"].items() if task in row["tasks"])


def compare_arms(arms: dict[str, list[dict]], task: str) -> dict:
    """Per arm, the per-seed values of the task's and its split's measures; and the target on the first two arms."""
    for name, probes in arms.items():
        for probe in probes:
            if task not in probe["actions"]:
                raise SystemExit(
                    f"arm {name!r}: {task} is not in the probed repo {probe['dataset']} (tasks: "
                    f"{', '.join(sorted(probe['actions']))}); pass one of them as --task."
                )
    split = split_of(next(iter(arms.values()))[0], task)
    out = {"task": task, "split": split, "arms": {}}
    for name, probes in arms.items():
        out["arms"][name] = {
            "task": {m: [task_value(p, task, m) for p in probes] for m, _ in TASK_MEASURES},
            "split": {m: [p["splits"][split].get(m, np.nan) for p in probes] for m, _ in SPLIT_MEASURES},
            "nc_trained": [trained_nc(p) for p in probes],
        }
    if len(arms) >= 2:
        (first, a), (second, b) = list(out["arms"].items())[:2]
        x, y = a["task"]["control_whole"], b["task"]["control_whole"]
        margin = float(np.mean(x) - np.mean(y))
        spread = float(max(np.ptp(x), np.ptp(y)))
        seeds = [len(x), len(y)]  # one seed has no spread to beat
        met = min(seeds) >= 2 and margin > spread
        out["target"] = {
            "arms": [first, second],
            "seeds": seeds,
            "margin": margin,
            "spread": spread,
            "met": met,
        }
        if min(seeds) >= 2 and np.var(x) + np.var(y) > 0:
            welch = stats.ttest_ind(x, y, equal_var=False)
            low, high = welch.confidence_interval(0.95)
            out["target"]["welch"] = {"low": float(low), "high": float(high), "p": float(welch.pvalue)}
    return out


def cell(values: list[float], measure: str) -> str:
    """Mean [95% t interval, clipped to the measure's range] (per seed)."""
    per_seed = " / ".join(probe_fmt((v, np.nan, np.nan), measure) for v in values)
    return f"{probe_fmt(probe_interval(values, measure), measure)} ({per_seed})"


def markdown(result: dict) -> str:
    names = list(result["arms"])
    lines = []
    for part, measures, title in (
        ("task", TASK_MEASURES, result["task"]),
        ("split", SPLIT_MEASURES, f"{result['split']} (mean over its tasks)"),
    ):
        lines += [f"| {title} | " + " | ".join(names) + " |", "|---|" + "---|" * len(names)]
        for measure, label in measures:
            cells = [cell(result["arms"][name][part][measure], measure) for name in names]
            lines.append(f"| {label} | " + " | ".join(cells) + " |")
        lines.append("")
    nc = "; ".join(f"{name} {cell(result['arms'][name]['nc_trained'], 'nc')}" for name in names)
    lines += [f"E_prt nearest-centroid accuracy over the trained tasks' held-out prompts (%): {nc}", ""]
    if target := result.get("target"):
        first, second = target["arms"]
        verdict = (
            f"the target (a margin larger than the spread) is {'met' if target['met'] else 'not met'}"
            if min(target["seeds"]) >= 2
            else "one seed in an arm has no spread: the target needs at least two seeds per arm"
        )
        lines.append(
            f"{result['task']} control whole: {first} - {second} = {100 * target['margin']:+.1f} points; spread over "
            f"seeds (larger range of the two arms, {' and '.join(map(str, target['seeds']))} seeds) "
            f"{100 * target['spread']:.1f} points: {verdict}."
        )
        if welch := target.get("welch"):
            lines.append(
                f"Welch's t-test of the difference: 95% interval [{100 * welch['low']:+.1f}, "
                f"{100 * welch['high']:+.1f}] points, p = {welch['p']:.3f} (two-sided)."
            )
    return "\n".join(lines) + "\n"


def main() -> None:
    cfg = draccus.parse(config_class=ProbeSeedsConfig)
    if not cfg.arms:
        raise SystemExit("Pass --arms='{NAME: [PROBE_DIR, ...], NAME2: [...]}' (jept-prompt-probe outputs).")
    arms = {name: [load_probe(path) for path in paths] for name, paths in cfg.arms.items()}
    print(markdown(compare_arms(arms, cfg.task)))


if __name__ == "__main__":
    main()
