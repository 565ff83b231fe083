"""The study's report: tables with intervals over training seeds, the pre-registered test, and plots."""

import json
import math
import re
from pathlib import Path

import draccus
import numpy as np

from lerobot_jept.evaluation.paper import PAPER_TABLE2
from lerobot_jept.evaluation.prompt_probe import MEASURES as PROBE_MEASURES
from lerobot_jept.evaluation.prompt_probe import scene_key
from lerobot_jept.evaluation.stats import interval, wilson
from lerobot_jept.study.config import MethodSpec, PreRegisteredTest, SplitSpec, StudyConfig, output_dir
from lerobot_jept.study.plan import checkpoint, run_folder, slug


def fmt(mean: float, low: float, high: float, digits: int = 1, scale: float = 1.0) -> str:
    if mean != mean:
        return "-"
    m, lo, hi = mean * scale, low * scale, high * scale
    if lo != lo:  # one seed: no interval
        return f"{m:.{digits}f}"
    return f"{m:.{digits}f} [{lo:.{digits}f}, {hi:.{digits}f}]"


def probe_interval(values: list[float], measure: str) -> tuple[float, float, float]:
    """:func:`interval` of a probe measure over seeds, clipped to its range (accuracies [0, 1], L_obs >= 0)."""
    mean, low, high = interval(values)
    top = math.inf if measure == "loss_obs" else 1.0
    return mean, max(low, 0.0), min(high, top)  # one seed: NaN bounds stay NaN


def probe_fmt(stats: tuple[float, float, float], measure: str) -> str:
    """L_obs as is (3 digits), accuracies in % (1 digit)."""
    scale, digits = (1.0, 3) if measure == "loss_obs" else (100.0, 1)
    return fmt(*stats, digits=digits, scale=scale)


def run_results(out: Path, split: SplitSpec, method: MethodSpec, seed: int) -> dict | None:
    """A run's ``jept-eval-suite`` results (``suite/results.json``); None before its suite has run."""
    path = run_folder(out, split, method, seed) / "suite/results.json"
    return json.loads(path.read_text()) if path.is_file() else None


def floor_per_task(out: Path, split: SplitSpec) -> dict:
    """The random 7-bin floor's outcomes per task of the split; empty before the floor has run."""
    path = out / slug(split.name) / "random_floor.done.json"
    return json.loads(path.read_text())["per_task"] if path.is_file() else {}


def probe_table(cfg: StudyConfig, split: SplitSpec) -> tuple[str, dict]:
    """The offline probe per split group, mean [95% interval] over seeds, per method."""
    out = output_dir(cfg)
    values: dict[str, dict[str, dict[str, list[float]]]] = {}
    for method in cfg.methods:
        for seed in cfg.seeds:
            results = run_results(out, split, method, seed)
            if results is None:
                continue
            probe = results.get("prompt_probe") or {}
            for group, row in probe.get("splits", {}).items():
                for measure in PROBE_MEASURES:
                    if measure in row:
                        values.setdefault(method.name, {}).setdefault(group, {}).setdefault(
                            measure, []
                        ).append(row[measure])
    if not values:
        return "", {}
    lines = [
        "| Method | Split | control whole (%) | control per-dim (%) | inverse whole (%) | inverse per-dim (%) "
        "| L_obs | a_{t-1} repeated, whole (%) | E_prt NC (%) | E_prt NC, trained tasks (%) "
        "| prompt swap changes action (%) | control whole under the swap (%) |",
        "|---|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|",
    ]
    summary: dict = {}
    for method, groups in values.items():
        for group, measures in groups.items():
            cells = []
            for measure in PROBE_MEASURES:
                stats = probe_interval(measures.get(measure, []), measure)
                summary.setdefault(method, {}).setdefault(group, {})[measure] = stats
                cells.append(probe_fmt(stats, measure))
            lines.append(f"| {method} | {group} | " + " | ".join(cells) + " |")
    return "\n".join(lines) + "\n", summary


def log_freq(cfg: StudyConfig, method: MethodSpec, folder: Path) -> int:
    """The run's ``log_freq``: from its checkpoint's config, or (a run kept without its checkpoints) from what
    the study gave ``lerobot-train``: the method's config file and the flags after it."""
    config = checkpoint(folder) / "train_config.json"
    if config.is_file():
        return json.loads(config.read_text()).get("log_freq", 1)
    freq = json.loads(Path(method.config).read_text()).get("log_freq", 200)  # LeRobot's default
    for arg in [*cfg.train_args, *method.args]:
        if arg.startswith("--log_freq="):
            freq = int(arg.split("=", 1)[1])
    return freq


def training_curves(cfg: StudyConfig, split: SplitSpec) -> dict[str, dict[str, list[list[float]]]]:
    """loss_obs / loss_act per logged step of every run, from the lerobot-train logs."""
    out = output_dir(cfg)
    curves: dict[str, dict[str, list[tuple[list[int], list[float]]]]] = {}
    for method in cfg.methods:
        for seed in cfg.seeds:
            folder = run_folder(out, split, method, seed)
            log = folder / "train.log"
            if not log.is_file():
                continue
            freq = log_freq(cfg, method, folder)
            series: dict[str, list[float]] = {}
            for line in log.read_text().splitlines():
                if line.startswith("$ "):
                    resumed = re.search(r"checkpoints/(\d+)/pretrained_model", line)
                    if "--resume=true" not in line:
                        series = {}  # the run restarted from scratch after a kill: its earlier lines are void
                    elif resumed:  # resumed from a checkpoint: what the killed run logged past it is void
                        series = {name: ys[: int(resumed.group(1)) // freq] for name, ys in series.items()}
                    continue
                if " step:" not in f" {line}":
                    continue
                for name in ("loss_obs", "loss_act"):
                    match = re.search(rf"\b{name}:([-+0-9.eE]+)", line)
                    if match:
                        series.setdefault(name, []).append(float(match.group(1)))
            for name, ys in series.items():
                steps = [freq * (i + 1) for i in range(len(ys))]
                curves.setdefault(method.name, {}).setdefault(name, []).append((steps, ys))
    return curves


def plot_curves(curves: dict, path: Path, title: str) -> bool:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    names = [n for n in ("loss_obs", "loss_act") if any(n in c for c in curves.values())]
    if not names:
        return False
    fig, axes = plt.subplots(1, len(names), figsize=(6 * len(names), 4), squeeze=False)
    colours = plt.rcParams["axes.prop_cycle"].by_key()["color"]
    for ax, name in zip(axes[0], names, strict=True):
        for i, (method, series) in enumerate(curves.items()):
            for j, (steps, values) in enumerate(series.get(name, [])):
                ax.plot(
                    steps,
                    values,
                    color=colours[i % len(colours)],
                    alpha=0.7,
                    label=method if j == 0 else None,
                )
        ax.set_xlabel("step")
        ax.set_ylabel(name)
        ax.set_title(f"{title}: {name} (one line per seed)")
        ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return True


def plot_table2(cfg: StudyConfig, rows: dict[int, dict[str, dict]], path: Path) -> None:
    """Success against the number of T_vid tasks (the paper's Table 2), per method, with the paper's JEPT."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 2, figsize=(11, 4))
    xs = sorted(rows)
    for ax, row in zip(axes, ("T_demo", "Unseen average"), strict=True):
        for method in cfg.methods:
            cells = [rows[x].get(method.name, {}).get(row) for x in xs]
            pts = [(x, c) for x, c in zip(xs, cells, strict=True) if c]
            if not pts:
                continue
            means = [c["mean"] for _, c in pts]
            err = [[c["mean"] - c["low"] for _, c in pts], [c["high"] - c["mean"] for _, c in pts]]
            ax.errorbar(
                [x for x, _ in pts],
                means,
                yerr=np.clip(err, 0, None),
                marker="o",
                capsize=3,
                label=method.name,
            )
        paper = [(x, PAPER_TABLE2[x][row]) for x in xs if x in PAPER_TABLE2]
        if paper and cfg.simulator == "metaworld":
            ax.plot(*zip(*paper, strict=True), "k--", marker="s", label="JEPT (paper)")
        ax.set_xlabel("number of video-only tasks (T_vid)")
        ax.set_ylabel(f"{row} success (%)")
        ax.set_ylim(0, 100)
        ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def write_report(cfg: StudyConfig) -> Path:
    """``report.md`` (and its plots) from the compare, suite and training outputs of the study."""
    out = output_dir(cfg)
    own = [
        f"{m.name} {m.eval_episodes}" for m in cfg.methods if m.eval_episodes not in (None, cfg.eval_episodes)
    ]
    steps_own = ", ".join(f"{m.name} {m.steps}" for m in cfg.methods if m.steps not in (None, cfg.steps))
    steps_own = f" ({steps_own})" if steps_own else ""
    episodes = f"{cfg.eval_episodes} evaluation episodes per task and seed" + (
        f" ({', '.join(own)})" if own else ""
    )
    lines = [
        f"# Study `{cfg.name}` ({cfg.simulator})",
        "",
        f"Methods: {', '.join(m.name for m in cfg.methods)}; training seeds {cfg.seeds}, {cfg.steps} steps each"
        f"{steps_own}; "
        f"{episodes} (env seeds from {cfg.eval_seed}). Success % "
        "is the mean over training seeds with a 95% Student's t interval over seeds (with one seed: a bootstrap "
        "interval over its evaluation episodes).",
        "",
    ]
    table2: dict[int, dict[str, dict]] = {}
    for split in cfg.splits:
        split_dir = out / slug(split.name)
        comparison_path = split_dir / "compare/comparison.json"
        lines += [f"## {split.name}: `{split.repo_id}`", ""]
        for name, tasks in (
            ("T_demo", split.demo_tasks),
            ("T_vid", split.video_tasks),
            ("T_unseen", split.unseen_tasks),
        ):
            lines.append(f"- {name}: {', '.join(tasks) or '(none)'}")
        lines.append("")
        if not comparison_path.is_file():
            lines += ["(not run yet)", ""]
            continue
        comparison = json.loads(comparison_path.read_text())
        floor_path = split_dir / "random_floor.done.json"
        floor = json.loads(floor_path.read_text()) if floor_path.is_file() else None
        lines += success_table(comparison, floor, split)
        lines += [f"![success]({comparison_path.parent.relative_to(out) / 'comparison.png'})", ""]
        probe, _ = probe_table(cfg, split)
        if probe:
            lines += [
                "Offline probe on the held-out `_probe` repo (action-bin accuracy of a_t: `control` = the action "
                "the policy would choose, `inverse` = JEPT's inverse dynamics from the real next frame; L_obs = "
                "JEPT's next-embedding error; E_prt NC = nearest-centroid accuracy of the prompt embedding over the "
                "tasks, held-out prompts, among all tasks and among the trained (demo and video) tasks alone; "
                "prompt swap = share of frames whose chosen action changes when the task's prompt is replaced by "
                "its scene-mate's, and the accuracy of the action then chosen), mean [95% interval] over seeds:",
                "",
                probe,
            ]
        figures = split_dir / "visualize"
        if (figures / "prompt_embeddings.png").is_file():
            lines += [
                "t-SNE of E_prt of every held-out probe episode used as a prompt (the paper's Figure 5) and of the "
                "observation embeddings along one episode of a demo, a video and an unseen task (Figure 3), first "
                "seed:",
                "",
                f"![prompt embeddings]({Path(slug(split.name)) / 'visualize/prompt_embeddings.png'}) "
                f"![observation embeddings]({Path(slug(split.name)) / 'visualize/observation_embeddings.png'})",
                "",
            ]
        curves = training_curves(cfg, split)
        if plot_curves(curves, split_dir / "training_curves.png", split.name):
            lines += [f"![training curves]({Path(slug(split.name)) / 'training_curves.png'})", ""]
        table2[len(split.video_tasks)] = {
            method: {row: cells.get(row) for row in ("T_demo", "Unseen average")}
            for method, cells in comparison["table"].items()
        }
    if len(cfg.splits) > 1 and table2:
        plot_table2(cfg, table2, out / "table2.png")
        lines += ["## Success against the number of video-only tasks", "", "![table 2](table2.png)", ""]
    text, summary = video_only_summary(cfg)
    if summary:
        (out / "video_only.json").write_text(json.dumps(summary, indent=2))
        lines += text
    if cfg.test is not None:
        text, verdict = preregistered_test(cfg)
        (out / "test.json").write_text(json.dumps(verdict, indent=2))
        lines += text
    report = out / "report.md"
    report.write_text("\n".join(lines))
    return report


def video_only_summary(cfg: StudyConfig) -> tuple[list[str], dict]:
    """Every method on every split's video-only tasks, read on the episodes all methods ran (the first E env
    seeds, E the smallest ``eval_episodes`` among them, so that every column sees the same episodes): successes
    per case and training seed, the mean over cases per seed, its mean [95% t] over the seeds that finished every
    case, and the p over those seeds against the first method: paired t for a method that evaluates the first
    method's checkpoints (``checkpoints_of``: the same checkpoints under another control setting) or trains its
    runs on (``continue_from``: the same runs, more steps), else Welch's.
    Exploratory beside the pre-registered test."""
    from scipy import stats

    out = output_dir(cfg)
    episodes = min(m.eval_episodes or cfg.eval_episodes for m in cfg.methods)
    cases = [(split, task) for split in cfg.splits for task in split.video_tasks]
    summary: dict[str, dict] = {}
    for method in cfg.methods:
        counts = {}
        for seed in cfg.seeds:
            row = []
            for split in cfg.splits:
                per_task = (run_results(out, split, method, seed) or {}).get("per_task", {})
                for task in split.video_tasks:
                    result = per_task.get(task)
                    row.append(None if result is None else int(sum(result["successes"][:episodes])))
            counts[seed] = row
        complete = {s: 100.0 * float(np.mean(row)) / episodes for s, row in counts.items() if None not in row}
        summary[method.name] = {"counts": counts, "seed_means": complete}
    if all(c is None for s in summary.values() for row in s["counts"].values() for c in row):
        return [], {}
    first = cfg.methods[0].name
    header = [f"{task.removesuffix('-v3')} ({split.name})" for split, task in cases]
    lines = [
        "## Video-only tasks, every split",
        "",
        f"Successes of {episodes} per training seed ({', '.join(map(str, cfg.seeds))}; env seeds from "
        f"{cfg.eval_seed}, the episodes every method ran), and the mean over the cases per seed: mean [95% t "
        f"interval] over the seeds that finished every case, Welch's p over seeds against {first} (paired t, "
        "marked *, for a method evaluating its checkpoints under another control setting or training its runs on). "
        "Exploratory: not the study's pre-registered test.",
        "",
        "| method | " + " | ".join(header) + " | mean % | per seed | p vs first |",
        "|---|" + "---|" * (len(header) + 3),
    ]
    by_seed = summary[first]["seed_means"]
    reference = list(by_seed.values())
    for method in cfg.methods:
        name, s = method.name, summary[method.name]
        cells = [
            " / ".join(
                "-" if s["counts"][seed][i] is None else str(s["counts"][seed][i]) for seed in cfg.seeds
            )
            for i in range(len(cases))
        ]
        values = list(s["seed_means"].values())
        mean, low, high = interval(values)
        low, high = max(low, 0.0), min(high, 100.0)  # NaN (one seed) stays NaN
        paired = first in (method.checkpoints_of, method.continue_from)
        if paired:  # the same checkpoints: each seed's difference, over the seeds both finished
            both = [seed for seed in s["seed_means"] if seed in by_seed]
            mine, theirs = [s["seed_means"][k] for k in both], [by_seed[k] for k in both]
            p = float(stats.ttest_rel(mine, theirs).pvalue) if len(both) > 1 else math.nan
        elif name != first and len(values) > 1 and len(reference) > 1:
            p = float(stats.ttest_ind(values, reference, equal_var=False).pvalue)
        else:
            p = math.nan
        s.update(mean=mean, low=low, high=high, p_vs_first=p, paired=paired)
        per_seed = ", ".join(f"{v:.1f}" for v in values) or "-"
        lines.append(
            f"| {name} | "
            + " | ".join(cells)
            + f" | {fmt(mean, low, high)} | {per_seed} | "
            + ("-" if p != p else f"{p:.2f}" + "*" * paired)
            + " |"
        )
    floors = []
    for split in cfg.splits:
        floor = floor_per_task(out, split)
        for task in split.video_tasks:
            outcomes = floor.get(task, {})
            floors.append(int(sum(outcomes["successes"][:episodes])) if "successes" in outcomes else None)
    floor_mean = 100.0 * float(np.mean(floors)) / episodes if None not in floors else math.nan
    lines.append(
        "| random 7-bin (floor) | "
        + " | ".join("-" if f is None else str(f) for f in floors)
        + f" | {fmt(floor_mean, math.nan, math.nan)} | | |"
    )
    pair_lines, pairs = per_pair(summary, [task for _, task in cases], floors, episodes)
    lines += ["", "![video-only tasks, every split](video_only.png)", *pair_lines]
    plot_video_only(summary, floor_mean, out / "video_only.png", episodes)
    return lines + [""], {
        "episodes": episodes,
        "cases": header,
        "methods": summary,
        "floor": floors,
        "pairs": pairs,
    }


def per_pair(
    summary: dict, tasks: list[str], floors: list, episodes: int
) -> tuple[list[str], dict[str, dict]]:
    """The video-only cases grouped by scene (a pair's two directions, from two splits): per method, the mean
    success over the pair's cases per training seed and its mean [95% t] over the seeds that finished them.
    Empty when no scene has more than one case."""
    scenes: dict[str, list[int]] = {}
    for i, task in enumerate(tasks):
        scenes.setdefault(scene_key(task), []).append(i)
    scenes = {scene: rows for scene, rows in scenes.items() if len(rows) > 1}
    if not scenes:
        return [], {}
    pairs: dict[str, dict] = {}
    lines = [
        "",
        "### Per scene pair",
        "",
        f"Both directions of each pair together: success % over the pair's cases ({episodes} episodes each), "
        "mean [95% t interval] over the training seeds that finished them.",
        "",
        "| method | " + " | ".join(scenes) + " |",
        "|---|" + "---|" * len(scenes),
    ]
    for name, s in summary.items():
        cells = []
        for scene, rows in scenes.items():
            values = [
                100.0 * float(np.mean([row[i] for i in rows])) / episodes
                for row in s["counts"].values()
                if None not in (row[i] for i in rows)
            ]
            mean, low, high = interval(values)
            pairs.setdefault(scene, {})[name] = {"seed_means": values, "mean": mean, "low": low, "high": high}
            cells.append(fmt(mean, max(low, 0.0), min(high, 100.0)))
        lines.append(f"| {name} | " + " | ".join(cells) + " |")
    cells = []
    for scene, rows in scenes.items():
        known = [floors[i] for i in rows]
        mean = math.nan if None in known else 100.0 * float(np.mean(known)) / episodes
        pairs[scene]["random 7-bin (floor)"] = {"mean": mean}
        cells.append(fmt(mean, math.nan, math.nan))
    lines.append("| random 7-bin (floor) | " + " | ".join(cells) + " |")
    return lines, pairs


def plot_video_only(summary: dict, floor_mean: float, path: Path, episodes: int) -> None:
    """The mean over the video-only cases per method: per training seed (dots) and over seeds (bars), the
    random floor's mean (a dashed line)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    names = list(summary)
    fig, ax = plt.subplots(figsize=(max(5.0, 1.2 * len(names) + 2), 3.8))
    for x, name in enumerate(names):
        values = list(summary[name]["seed_means"].values())
        ax.bar(x, np.mean(values) if values else 0.0, 0.6, alpha=0.85)
        ax.plot([x] * len(values), values, "k.", markersize=6)
    if floor_mean == floor_mean:
        ax.axhline(floor_mean, color="r", linestyle="--", label="random 7-bin")
        ax.legend(fontsize=8)
    ax.set_xticks(range(len(names)), names, fontsize=8, rotation=15)
    ax.set_ylabel(f"video-only success (%, {episodes} episodes per case)")
    ax.set_ylim(0, 100)
    ax.set_title("mean over every split's video-only tasks (dots: training seeds)")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def case_successes(cfg: StudyConfig, split: SplitSpec, method: str, task: str) -> tuple[list, list]:
    """Per training seed with a finished suite: the task's success % with its own prompt, and under the
    scene-mate's prompt (when the suite ran it)."""
    spec = next(m for m in cfg.methods if m.name == method)
    own, mate = [], []
    for seed in cfg.seeds:
        row = (run_results(output_dir(cfg), split, spec, seed) or {}).get("per_task", {}).get(task)
        if row is None:
            continue
        own.append(row["pc_success"])
        if "scene_mate" in row:
            mate.append(row["scene_mate"]["pc_success"])
    return own, mate


def preregistered_test(cfg: StudyConfig) -> tuple[list[str], dict]:
    """The study file's test on the finished runs: one row per case, and the verdict."""
    from scipy import stats

    test = cfg.test
    out = output_dir(cfg)
    cases, lines = [], []
    for split in cfg.splits:
        floor = floor_per_task(out, split)
        for task in split.video_tasks:
            arm, arm_mate = case_successes(cfg, split, test.method, task)
            base, _ = case_successes(cfg, split, test.baseline, task)
            margin = float(np.mean(arm) - np.mean(base)) if arm and base else math.nan
            spread = max(np.ptp(arm), np.ptp(base)) if arm and base else math.nan
            p = (
                float(stats.ttest_ind(arm, base, equal_var=False).pvalue)
                if len(arm) > 1 and len(base) > 1 and (np.ptp(arm) or np.ptp(base))
                else math.nan
            )
            outcomes = floor.get(task, {}).get("successes", [])
            floor_high = wilson(sum(outcomes), len(outcomes))[1]
            mate = float(np.mean(arm_mate)) if arm_mate else math.nan
            cases.append(
                {
                    "split": split.name,
                    "task": task,
                    "method_seeds": arm,
                    "baseline_seeds": base,
                    "margin": margin,
                    "seed_spread": float(spread),
                    "passes": bool(margin > spread),
                    "welch_p": p,
                    "scene_mate_success": mate,
                    "floor_upper": floor_high,
                    "within_floor": bool(mate <= floor_high + test.floor_margin),
                }
            )
    done = [c for c in cases if c["method_seeds"] and c["baseline_seeds"]]
    mean = float(np.mean([np.mean(c["method_seeds"]) for c in done])) if done else math.nan
    passed = sum(c["passes"] for c in done)
    verdict = {
        "test": draccus.encode(test),
        "cases": cases,
        "cases_run": len(done),
        "cases_passed": passed,
        "mean_success": mean,
        "holds": bool(
            len(done) == len(cases)
            and passed >= test.min_cases
            and mean >= test.goal_mean
            and all(c["within_floor"] for c in done)
        ),
    }
    lines += [
        "## The pre-registered test",
        "",
        f"Fixed in the study file before it ran: on each video-only task (a case), {test.method} against "
        f"{test.baseline} over training seeds; a case passes when the difference of the means exceeds the "
        f"larger seed range. The hypothesis needs at least {test.min_cases} cases passing (of {len(cases)}), a mean "
        f"of at least {test.goal_mean:.0f}% over the cases, and every case under the scene-mate's prompt within "
        f"its random floor (upper end of the floor's 95% Wilson interval + {test.floor_margin:.0f}).",
        "",
        f"| split | video-only task | {test.method}, per seed | {test.baseline}, per seed | margin | seed range "
        "| passes | Welch p | under the scene-mate's prompt | random floor, upper 95% |",
        "|---|---|---|---|---:|---:|---|---:|---:|---:|",
    ]
    for c in cases:
        seeds = [" / ".join(f"{v:.0f}" for v in c[k]) or "-" for k in ("method_seeds", "baseline_seeds")]
        lines.append(
            f"| {c['split']} | {c['task']} | {seeds[0]} | {seeds[1]} | {c['margin']:+.1f} | {c['seed_spread']:.1f} "
            f"| {'yes' if c['passes'] else 'no'} | {c['welch_p']:.3f} | {c['scene_mate_success']:.1f} "
            f"| {c['floor_upper']:.1f} |"
        )
    lines += [
        "",
        f"Cases run {len(done)} of {len(cases)}, passing {passed}; mean success of {test.method} over the cases "
        f"{mean:.1f}%. The hypothesis **{'holds' if verdict['holds'] else 'does not hold'}**.",
        "",
    ]
    if done:
        plot_test(test, done, out / "test.png")
        lines += ["![the test's cases](test.png)", ""]
    return lines, verdict


def plot_test(test: PreRegisteredTest, cases: list[dict], path: Path) -> None:
    """Per case: the method's and the baseline's success per training seed (dots) and mean (bars), the
    method's under the scene-mate's prompt, and the upper end of the random floor's interval (a dash)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(max(6.0, 1.3 * len(cases) + 2), 4))
    xs = np.arange(len(cases))
    width = 0.27
    bars = (
        (test.method, "method_seeds", -width),
        (test.baseline, "baseline_seeds", 0.0),
    )
    for label, key, offset in bars:
        means = [np.mean(c[key]) for c in cases]
        ax.bar(xs + offset, means, width, alpha=0.85, label=f"{label} (dots: seeds)")
        for x, c in zip(xs, cases, strict=True):
            ax.plot([x + offset] * len(c[key]), c[key], "k.", markersize=5)
    mates = [c["scene_mate_success"] for c in cases]
    ax.bar(
        xs + width,
        np.nan_to_num(mates),
        width,
        hatch="//",
        fill=False,
        label=f"{test.method}, scene-mate's prompt",
    )
    ax.plot(
        xs, [c["floor_upper"] for c in cases], "r_", markersize=28, mew=2, label="random floor, upper 95%"
    )
    ax.set_xticks(xs, [f"{c['task'].removesuffix('-v3')}\n({c['split']})" for c in cases], fontsize=8)
    ax.set_ylabel("success (%)")
    ax.set_ylim(0, 100)
    ax.set_title("the pre-registered test: each video-only task over training seeds")
    ax.legend(fontsize=7, loc="upper right")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def success_table(comparison: dict, floor: dict | None, split: SplitSpec) -> list[str]:
    """The comparison's rows (mean [interval] per method, the paper's columns) with the random floor."""
    from lerobot_jept.evaluation.suite import SCENE_MATE_ROW, summarise

    table, paper = comparison["table"], comparison.get("paper") or {}
    rows = list(next(iter(table.values())))
    floor_rows = {}
    if floor:
        floor_rows = summarise(
            comparison["split"], {t: r["pc_success"] for t, r in floor["per_task"].items()}
        )
        floor_rows[SCENE_MATE_ROW] = floor_rows.get("T_vid", math.nan)  # another prompt, the same tasks
    header = ["Row"] + list(table) + (["Random 7-bin"] if floor else []) + [f"{m} (paper)" for m in paper]
    lines = ["| " + " | ".join(header) + " |", "|---|" + "---:|" * (len(header) - 1)]
    for row in rows:
        cells = [fmt(table[m][row]["mean"], table[m][row]["low"], table[m][row]["high"]) for m in table]
        if floor:
            cells.append(f"{floor_rows.get(row, math.nan):.1f}")
        cells += [f"{paper[m][row]:.1f}" if row in paper[m] else "-" for m in paper]
        lines.append(f"| {row} | " + " | ".join(cells) + " |")
    if floor:
        lines += [
            "",
            f"Random 7-bin: a uniformly random bin per action dimension, {floor['episodes']} episodes per "
            "task on the same env seeds.",
        ]
    if comparison.get("paper_source"):
        lines.append(f"Paper columns: {comparison['paper_source']}.")
    return lines + [""]
