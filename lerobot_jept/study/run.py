"""``jept-study``: the paper's experiments as one resumable command.

    jept-study --config=examples/studies/cpu_small.json [--output_dir=DIR] [--device=cpu|cuda] [--parallel=2]

A study file (JSON, read with draccus into :class:`StudyConfig`; every field can also be given on the command
line, e.g. ``--seeds='[1000]'``) names the simulator, one or more splits (several: the paper's Table 2), the
build sizes, the methods, the training seeds and steps, and the evaluation episodes. The study runs the real
entry points in order and prints each command before it runs it:

1. per split, the builder (``jept-build-metaworld`` / ``jept-build-robosuite``): ``_demo``, ``_video``,
   ``_prompts``, ``_probe`` and ``_mix`` repos under ``$HF_LEROBOT_HOME`` (shared with any other study or
   command that builds the same flags);
2. per split, the random 7-bin policy's success on every task (the floor), when ``random_episodes`` > 0;
3. per split, method and seed: ``lerobot-train`` (for BC+IDM: ``lerobot-train`` of the ``jept_idm``, ``jept-relabel``
   of the mix, then ``lerobot-train`` of ``jept_dt_star`` on the relabelled repo), then ``jept-eval-suite`` (LeRobot's
   eval on every task, plus the offline probe on the build's ``_probe`` repo);
4. per split, ``jept-compare`` over the methods and seeds;
5. ``report.md`` with the tables (mean and 95% interval over seeds, the paper's numbers beside ours on the
   paper's split, the random floor), the offline probe per split, and plots: grouped success bars, training
   curves of loss_obs / loss_act per method, and (several splits) success against the number of video tasks.

With ``parallel`` N > 1, up to N runs (a method's seed) go at once, each with cores // N torch threads; the
split-level steps (build, floor, figures, comparison) run alone. One progress bar, in estimated seconds of work,
gives the ETA.

Resumable: every finished step leaves a marker (``<step>.done.json``) and is skipped on re-run; a training run
killed after a checkpoint resumes from it (``lerobot-train --resume=true``), one killed before restarts clean.
Each command's output goes to a log file next to its outputs (printed on failure).
"""

import json
import logging
import math
import os
import re
import shlex
import shutil
import subprocess
import sys
import threading
import time
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from pathlib import Path

import draccus
import numpy as np
from tqdm import tqdm

from lerobot_jept.evaluation.paper import PAPER_TABLE2
from lerobot_jept.evaluation.prompt_probe import MEASURES as PROBE_MEASURES
from lerobot_jept.evaluation.stats import interval, wilson


@dataclass
class SplitSpec:
    """One build: its ORG/NAME and its task split (T_demo / T_vid / T_unseen)."""

    name: str = "split"  # folder of its runs and label in the report
    repo_id: str = "local/study"
    demo_tasks: list[str] = field(default_factory=list)
    video_tasks: list[str] = field(default_factory=list)
    unseen_tasks: list[str] = field(default_factory=list)


@dataclass
class BuildSpec:
    """Builder flags shared by every split of the study (``args``: any further builder flags)."""

    episodes_per_task: int = 30
    prompts_per_task: int = 4
    probe_episodes_per_task: int = 4
    play_episodes_per_task: int = 0  # labelled play episodes per demo and video task's scene (in the mix)
    image_size: int = 96
    seed: int = 0
    num_workers: int = 2
    args: list[str] = field(default_factory=list)


@dataclass
class MethodSpec:
    """One column of the tables. ``kind``: ``train`` (``lerobot-train`` with ``config`` on the split's ``data``
    repo: ``mix``; ``demo``; or ``labelled``, every labelled frame of the mix without the videos, i.e. ``_demo``
    plus ``_play`` when the build has play episodes) or ``bc_idm`` (a ``jept_idm`` from ``idm_config`` on the
    labelled frames, ``jept-relabel`` of ``_mix``, then ``config``, a ``jept_dt_star`` config, on the relabelled
    repo). ``args``: ``lerobot-train`` flags of this method (a ``jept`` variant is ``jept`` with overrides).
    ``eval_episodes`` (default: the study's) and ``suite_args`` (added to the study's) set its evaluation."""

    name: str = "JEPT"
    kind: str = "train"
    config: str = "examples/configs/train_jept_small_cpu.json"
    data: str = "mix"
    args: list[str] = field(default_factory=list)
    idm_config: str = "examples/configs/train_idm_small_cpu.json"
    idm_args: list[str] = field(default_factory=list)
    eval_episodes: int | None = None
    suite_args: list[str] = field(default_factory=list)


@dataclass
class PreRegisteredTest:
    """The study's test, written in the study file before it runs.

    A case is one video-only task of one split (a scene pair in one direction). The primary measure is the
    case's success rate in the simulator, one value per training seed: seeds, not episodes, are the unit (a
    checkpoint's episodes share it). ``method`` passes a case when its mean over seeds exceeds ``baseline``'s
    (the same recipe on the same data without the videos) by more than the larger of the two arms' seed ranges.
    The hypothesis holds when at least ``min_cases`` cases pass, the mean over all cases reaches ``goal_mean``
    %, and under the scene-mate's prompt (``--scene_mate_prompts``) every case's success is at most
    ``floor_margin`` points above the upper end of its random floor's 95% Wilson interval (the prompt, not the
    scene, drives the behaviour). Welch's p over seeds is reported beside each case."""

    method: str = ""
    baseline: str = ""
    min_cases: int = 6
    goal_mean: float = 50.0
    floor_margin: float = 0.0


@dataclass
class StudyConfig:
    name: str = "study"
    simulator: str = "metaworld"  # metaworld | robosuite
    splits: list[SplitSpec] = field(default_factory=list)
    build: BuildSpec = field(default_factory=BuildSpec)
    methods: list[MethodSpec] = field(default_factory=list)
    seeds: list[int] = field(default_factory=lambda: [1000, 2000, 3000])
    steps: int = 1000
    save_freq: int = 500  # checkpoints a killed run resumes from
    train_args: list[str] = field(default_factory=list)  # lerobot-train flags of every run
    eval_episodes: int = 10  # per task
    eval_batch_size: int = 10
    eval_seed: int = 1000
    eval_episode_length: int | None = None  # default: the build's max_episode_steps
    suite_args: list[str] = field(
        default_factory=list
    )  # jept-eval-suite flags of every run (e.g. --splits=[video])
    # The test fixed before the study runs (see PreRegisteredTest); None for a study without one.
    test: PreRegisteredTest | None = None
    random_episodes: int = 20  # per task, for the random 7-bin floor; 0 skips it
    output_dir: Path | None = None  # default: outputs/study/<name>
    device: str = "cpu"
    # Runs (one method's seed: its training and evaluation) at once, each with cores // parallel torch threads.
    # On a 2-core CPU two one-thread runs do about 1.3-1.5 times the work of one two-thread run.
    parallel: int = 1


class StudyError(RuntimeError):
    pass


# ---------------------------------------------------------------------------------------------------------
# The plan: every step with its command (or function) and the marker that says it is done.


@dataclass
class Step:
    key: str  # unique, also the marker's name
    what: str  # shown on the progress bar
    folder: Path  # outputs and log
    command: list[str] | None = None
    function: Callable[[], dict] | None = None
    prepare: Callable[[], list[str] | None] | None = None  # before running: may replace the command (resume)
    always: bool = False  # re-run every time (cheap summaries)

    signature: list[str] | None = None  # what the marker must record (default: the command)

    @property
    def marker(self) -> Path:
        return self.folder / f"{self.key.split('/')[-1]}.done.json"

    @property
    def planned(self) -> list[str]:
        return self.signature or self.command or []

    def done(self) -> bool:
        """Finished by an earlier run of the same study; a marker of another command is an error (the output
        folder holds another study's runs), never silently reused or overwritten."""
        if self.always or not self.marker.is_file():
            return False
        recorded = json.loads(self.marker.read_text()).get("planned")
        if recorded != self.planned:
            raise StudyError(
                f"{self.marker} was written for another command:\n  {shlex.join(recorded or [])}\nnow:\n  "
                f"{shlex.join(self.planned)}\nThe study file changed since that run: pass another --output_dir, "
                f"or delete {self.folder} to redo it."
            )
        return True


def output_dir(cfg: StudyConfig) -> Path:
    return Path(cfg.output_dir) if cfg.output_dir else Path("outputs/study") / cfg.name


def lerobot_home() -> Path:
    from lerobot.utils.constants import HF_LEROBOT_HOME

    return Path(HF_LEROBOT_HOME)


def bin_path(name: str) -> str:
    return str(Path(sys.prefix) / "bin" / name)


def validate(cfg: StudyConfig) -> None:
    if cfg.simulator not in ("metaworld", "robosuite"):
        raise StudyError(f"simulator must be metaworld or robosuite, got {cfg.simulator!r}.")
    if not cfg.splits or not cfg.methods or not cfg.seeds:
        raise StudyError("The study file must name at least one split, one method and one seed.")
    for names, what in (([s.name for s in cfg.splits], "split"), ([m.name for m in cfg.methods], "method")):
        if len(set(names)) != len(names):
            raise StudyError(f"Two {what}s share a name in {names}: names are folders and columns.")
    for m in cfg.methods:
        if m.kind not in ("train", "bc_idm") or m.data not in DATA:
            raise StudyError(
                f"Method {m.name!r}: kind must be train or bc_idm and data one of {DATA} (got {m.kind}, {m.data})."
            )
        for path in [m.config] + ([m.idm_config] if m.kind == "bc_idm" else []):
            if not Path(path).is_file():
                raise StudyError(
                    f"Method {m.name!r}: train config {path} does not exist (paths are relative to "
                    "the folder jept-study runs in)."
                )
    names = [m.name for m in cfg.methods]
    if cfg.test is not None and not {cfg.test.method, cfg.test.baseline} <= set(names):
        raise StudyError(
            f"The test compares {cfg.test.method!r} with {cfg.test.baseline!r}; both must be methods of the study "
            f"({names})."
        )
    if cfg.test is not None and not any("--scene_mate_prompts=true" in m.suite_args for m in cfg.methods):
        raise StudyError(
            "The test reads the method's success under the scene-mate's prompt: give its method "
            '"suite_args": ["--scene_mate_prompts=true"].'
        )
    if cfg.steps < 1 or cfg.eval_episodes < 1:
        raise StudyError("steps and eval_episodes must be at least 1.")
    if cfg.device not in ("cpu", "cuda", "mps"):
        raise StudyError(f"--device must be cpu, cuda or mps, got {cfg.device!r}.")
    if cfg.parallel < 1:
        raise StudyError(f"--parallel is the number of runs at once, at least 1 (got {cfg.parallel}).")


DATA = ("mix", "demo", "labelled")


def labelled_repo(cfg: StudyConfig, split: SplitSpec) -> str:
    """Every labelled frame of the split's build: ``_demo``, plus ``_play`` when it has play episodes (mixed by
    the split's ``labelled`` step)."""
    return f"{split.repo_id}_labelled" if cfg.build.play_episodes_per_task else f"{split.repo_id}_demo"


def slug(name: str) -> str:
    return re.sub(r"[^A-Za-z0-9_.-]+", "_", name)


def build_command(cfg: StudyConfig, split: SplitSpec) -> list[str]:
    b = cfg.build
    return [
        bin_path(f"jept-build-{cfg.simulator}"),
        f"--repo_id={split.repo_id}",
        f"--demo_tasks=[{', '.join(split.demo_tasks)}]",
        f"--video_tasks=[{', '.join(split.video_tasks)}]",
        f"--unseen_tasks=[{', '.join(split.unseen_tasks)}]",
        f"--episodes_per_task={b.episodes_per_task}",
        f"--prompts_per_task={b.prompts_per_task}",
        f"--probe_episodes_per_task={b.probe_episodes_per_task}",
        *([f"--play_episodes_per_task={b.play_episodes_per_task}"] if b.play_episodes_per_task else []),
        f"--image_size={b.image_size}",
        f"--seed={b.seed}",
        f"--num_workers={b.num_workers}",
        *b.args,
    ]


def train_step(
    cfg: StudyConfig,
    key: str,
    folder: Path,
    config: str,
    data: list[str],
    seed: int,
    extra: list[str],
    prompts: str | None,
) -> Step:
    """``lerobot-train`` into ``folder/train``; resumes from its last checkpoint after a kill."""
    out = folder / "train"
    command = [
        bin_path("lerobot-train"),
        f"--config_path={config}",
        *data,
        *([f"--policy.prompt_repo_id={prompts}"] if prompts else []),
        f"--seed={seed}",
        f"--steps={cfg.steps}",
        f"--save_freq={min(cfg.save_freq, cfg.steps)}",
        f"--output_dir={out}",
        f"--policy.device={cfg.device}",
        *cfg.train_args,
        *extra,
    ]

    def prepare() -> list[str] | None:
        last = out / "checkpoints/last/pretrained_model/train_config.json"
        if last.is_file():  # killed after a checkpoint: LeRobot's own resume, from the numbered checkpoint
            # `last` points at (so the log says which step the run resumed from: training_curves)
            resolved = out / "checkpoints" / (out / "checkpoints/last").resolve().name
            config = resolved / "pretrained_model/train_config.json"
            return [bin_path("lerobot-train"), f"--config_path={config}", "--resume=true"]
        shutil.rmtree(out, ignore_errors=True)  # killed before any checkpoint: start clean
        return None

    return Step(key, key, folder, command, prepare=prepare)


def checkpoint(folder: Path) -> Path:
    return folder / "train/checkpoints/last/pretrained_model"


def run_folder(out: Path, split: SplitSpec, method: MethodSpec, seed: int) -> Path:
    return out / slug(split.name) / slug(method.name) / f"seed{seed}"


def plan(cfg: StudyConfig) -> list[Step]:
    out = output_dir(cfg)
    steps = []
    for split in cfg.splits:
        split_dir = out / slug(split.name)
        steps.append(
            Step(f"{split.name}/build", f"build {split.repo_id}", split_dir, build_command(cfg, split))
        )
        if cfg.build.play_episodes_per_task:
            steps.append(
                Step(
                    f"{split.name}/labelled",
                    f"labelled frames {split.repo_id}",
                    split_dir,
                    [
                        bin_path("jept-mix"),
                        f"--demo_repo_ids=[{split.repo_id}_demo, {split.repo_id}_play]",
                        f"--output_repo_id={labelled_repo(cfg, split)}",
                    ],
                    prepare=lambda split=split: shutil.rmtree(
                        lerobot_home() / labelled_repo(cfg, split), ignore_errors=True
                    ),
                )
            )
        if cfg.random_episodes > 0:
            steps.append(
                Step(
                    f"{split.name}/random_floor",
                    f"random floor {split.name}",
                    split_dir,
                    function=lambda split=split: random_floor(cfg, split),
                    signature=[
                        "random_floor",
                        f"episodes={cfg.random_episodes}",
                        f"seed={cfg.eval_seed}",
                        f"length={cfg.eval_episode_length}",
                    ],
                )
            )
        for seed in cfg.seeds:  # seed by seed: a study cut short still compares every method
            for method in cfg.methods:
                folder = run_folder(out, split, method, seed)
                key = f"{split.name}/{method.name}/seed{seed}"
                prompts = f"{split.repo_id}_prompts"
                if method.kind == "bc_idm":
                    idm = folder / "idm"
                    demo = [f"--dataset.repo_id={labelled_repo(cfg, split)}"]
                    steps.append(
                        train_step(
                            cfg, f"{key}/idm", idm, method.idm_config, demo, seed, method.idm_args, None
                        )
                    )
                    relabelled = f"{split.repo_id}_mix_idm"
                    relabel_root = folder / "relabelled"
                    steps.append(
                        Step(
                            f"{key}/relabel",
                            f"{key}/relabel",
                            folder,
                            [
                                bin_path("jept-relabel"),
                                f"--policy.path={checkpoint(idm)}",
                                f"--dataset.repo_id={split.repo_id}_mix",
                                f"--output_repo_id={relabelled}",
                                f"--output_root={relabel_root}",
                                f"--heldout_repo_id={split.repo_id}_probe",
                            ],
                            prepare=lambda root=relabel_root: shutil.rmtree(root, ignore_errors=True),
                        )
                    )
                    data = [f"--dataset.repo_id={relabelled}", f"--dataset.root={relabel_root}"]
                elif method.data == "labelled":
                    data = [f"--dataset.repo_id={labelled_repo(cfg, split)}"]
                else:
                    data = [f"--dataset.repo_id={split.repo_id}_{method.data}"]
                steps.append(
                    train_step(cfg, f"{key}/train", folder, method.config, data, seed, method.args, prompts)
                )
                episodes = method.eval_episodes or cfg.eval_episodes
                suite = [
                    bin_path("jept-eval-suite"),
                    f"--policy.path={checkpoint(folder)}",
                    f"--policy.device={cfg.device}",
                    f"--dataset.repo_id={split.repo_id}_mix",
                    f"--n_episodes={episodes}",
                    f"--batch_size={min(cfg.eval_batch_size, episodes)}",
                    f"--seed={cfg.eval_seed}",
                    f"--output_dir={folder / 'suite'}",
                ]
                if cfg.eval_episode_length:
                    suite.append(f"--episode_length={cfg.eval_episode_length}")
                suite += [*cfg.suite_args, *method.suite_args]
                steps.append(Step(f"{key}/suite", f"{key}/eval", folder, suite))
        steps += visualize_steps(cfg, split, split_dir)
        runs = {m.name: [str(run_folder(out, split, m, s) / "suite") for s in cfg.seeds] for m in cfg.methods}
        steps.append(
            Step(
                f"{split.name}/compare",
                f"compare {split.name}",
                split_dir,
                [
                    bin_path("jept-compare"),
                    f"--runs={json.dumps(runs)}",
                    f"--output_dir={split_dir / 'compare'}",
                ],
                always=True,
            )
        )
    return steps


def policy_type(method: MethodSpec) -> str:
    return json.loads(Path(method.config).read_text())["policy"]["type"]


def visualize_steps(cfg: StudyConfig, split: SplitSpec, split_dir: Path) -> list[Step]:
    """``jept-visualize`` of the first JEPT method's first seed against the first other method's, on the probe
    repo (Figures 3 and 5). Drawn once per split, with the seed list's first seed at that time."""
    jept = [m for m in cfg.methods if policy_type(m) == "jept"]
    others = [m for m in cfg.methods if policy_type(m) != "jept"]
    if not jept:
        return []
    seed = cfg.seeds[0]
    command = [
        bin_path("jept-visualize"),
        f"--policy.path={checkpoint(run_folder(output_dir(cfg), split, jept[0], seed))}",
        f"--policy.device={cfg.device}",
        f"--dataset.repo_id={split.repo_id}_probe",
        f"--output_dir={split_dir / 'visualize'}",
    ]
    if others:
        command.insert(
            3, f"--baseline.path={checkpoint(run_folder(output_dir(cfg), split, others[0], seed))}"
        )
        command.insert(4, f"--baseline.device={cfg.device}")
    # the marker names the methods, not the seed: a study resumed or extended with another seed list keeps the
    # figures of the seed they were drawn with
    signature = ["jept-visualize", split.name, jept[0].name, *[m.name for m in others[:1]]]
    return [
        Step(
            f"{split.name}/visualize", f"t-SNE figures {split.name}", split_dir, command, signature=signature
        )
    ]


# ---------------------------------------------------------------------------------------------------------
# Running it.


# A step's seconds before any step of its kind has finished, on a 2-core CPU: per training step for ``train`` and
# ``idm``, per episode and task for ``suite``, else per step. Replaced by what finished steps took.
PRIOR_SECONDS = {
    "train": 0.9,
    "idm": 0.3,
    "suite": 5.0,
    "build": 900.0,
    "random_floor": 150.0,
    "relabel": 120.0,
}


def cost_key(step: Step) -> tuple[str, ...]:
    """What a step's cost is estimated from: (method, kind) for a run's steps, (kind,) for a split's."""
    run, kind = run_of(step), step.key.split("/")[-1]
    return (run[1], kind) if run else (kind,)


def recorded_seconds(step: Step) -> float | None:
    if step.always or not step.marker.is_file():
        return None
    return json.loads(step.marker.read_text()).get("seconds")


def estimate_seconds(cfg: StudyConfig, steps: list[Step]) -> list[float]:
    """Each step's seconds: what it took, for a finished one; else the mean of the finished steps of its method
    and kind, else of its kind, else a prior (:data:`PRIOR_SECONDS`)."""
    recorded = [recorded_seconds(step) for step in steps]  # each marker read once
    seen: dict[tuple[str, ...], list[float]] = {}
    for step, seconds in zip(steps, recorded, strict=True):
        if seconds is not None:
            key = cost_key(step)
            seen.setdefault(key, []).append(seconds)
            if len(key) > 1:
                seen.setdefault(key[-1:], []).append(seconds)
    tasks = max(len([*s.demo_tasks, *s.video_tasks, *s.unseen_tasks]) for s in cfg.splits)
    scale = {"train": cfg.steps, "idm": cfg.steps, "suite": cfg.eval_episodes * tasks}
    estimates = []
    for step, seconds in zip(steps, recorded, strict=True):
        if seconds is None:
            key = cost_key(step)
            known = seen.get(key) or seen.get(key[-1:])
            kind = key[-1]
            seconds = float(np.mean(known)) if known else PRIOR_SECONDS.get(kind, 10.0) * scale.get(kind, 1)
        estimates.append(seconds)
    return estimates


class StudyProgress:
    """One bar over the whole study, counted in estimated seconds of work so that its ETA means something (a
    build or a training run weighs what it takes, a summary nothing); it moves while steps run, each up to its
    estimate, and the estimates are renewed from every finished step. Safe to call from several threads."""

    def __init__(self, cfg: StudyConfig, steps: list[Step], done: list[bool]):
        self.cfg, self.steps = cfg, steps
        self.completed = {i for i, d in enumerate(done) if d}
        self.estimates = estimate_seconds(cfg, steps)
        self.running_since: dict[int, float] = {}
        self.lock = threading.Lock()
        # in a log file (not a terminal) every redraw stays: redraw while a step runs every 5 minutes, not 10 s
        self.redraw_every = 0.0 if sys.stderr.isatty() else 300.0
        self.shown_at = -math.inf
        self.bar = tqdm(
            total=max(sum(self.estimates), 1.0),
            initial=self.done_seconds(),
            desc="study",
            bar_format="{desc}: {percentage:3.0f}%|{bar}| [{elapsed}<{remaining}{postfix}]",
            smoothing=0,
        )

    def done_seconds(self) -> float:
        return sum(self.estimates[i] for i in self.completed)

    def start(self, step: Step) -> None:
        with self.lock:
            self.running_since[self.steps.index(step)] = time.perf_counter()
            self._show()

    def running(self) -> None:
        """The bar moves with the running steps, each at most to 95% of its estimate."""
        with self.lock:
            if time.perf_counter() - self.shown_at >= self.redraw_every:
                self._show()

    def finish(self, step: Step) -> None:
        with self.lock:
            index = self.steps.index(step)
            self.running_since.pop(index, None)
            self.completed.add(index)
            self.estimates = estimate_seconds(self.cfg, self.steps)
            self.bar.total = max(sum(self.estimates), 1.0)
            self._show()

    def _show(self) -> None:
        now = self.shown_at = time.perf_counter()
        self.bar.n = self.done_seconds() + sum(
            min(now - since, 0.95 * self.estimates[i]) for i, since in self.running_since.items()
        )
        names = ", ".join(self.steps[i].what for i in self.running_since)
        self.bar.set_postfix_str(
            f"{len(self.completed)}/{len(self.steps)} steps done; {names}", refresh=False
        )
        self.bar.refresh()

    def write(self, text: str) -> None:
        self.bar.write(text)


def run_step(step: Step, progress: StudyProgress, threads: int | None = None) -> dict:
    """Run one step (its command with ``threads`` torch threads, when given) and write its marker."""
    step.folder.mkdir(parents=True, exist_ok=True)
    log = step.folder / f"{step.key.split('/')[-1]}.log"
    start = time.perf_counter()
    command = step.command
    if step.prepare is not None:
        command = step.prepare() or command
    if step.function is not None:
        progress.write(f"[{step.key}] (in process)")
        info = step.function()
    else:
        progress.write(f"\n$ {shlex.join(command)}")
        env = {**os.environ, "MUJOCO_GL": os.environ.get("MUJOCO_GL", "egl")}
        if threads:
            env.update(OMP_NUM_THREADS=str(threads), MKL_NUM_THREADS=str(threads))
        with open(log, "a") as f:
            f.write(f"\n$ {shlex.join(command)}\n")
            f.flush()
            process = subprocess.Popen(command, stdout=f, stderr=subprocess.STDOUT, env=env)
            while True:
                try:
                    code = process.wait(timeout=10)
                    break
                except subprocess.TimeoutExpired:
                    progress.running()
        if code != 0:
            tail = "\n".join(log.read_text().splitlines()[-25:])
            raise StudyError(
                f"Step {step.key} failed (exit {code}); its log is {log}. Fix the cause and re-run the same "
                f"jept-study command: finished steps are kept.\n--- last lines of the log ---\n{tail}"
            )
        info = {"command": command}
    info.update(planned=step.planned, seconds=time.perf_counter() - start)
    if not step.always:  # written whole or not at all: a kill, or a reader in another thread, sees no half
        partial = step.marker.with_suffix(".partial")
        partial.write_text(json.dumps(info, indent=2))
        os.replace(partial, step.marker)
    return info


def run_of(step: Step) -> tuple[str, ...] | None:
    """The run (split, method, seed) a step belongs to; None for a split's own steps."""
    parts = step.key.split("/")
    return tuple(parts[:3]) if len(parts) == 4 else None


def step_groups(steps: list[Step]) -> list[list[list[Step]]]:
    """The steps in the plan's order as groups that run one after the other; a group is either one split-level
    step (build, floor, figures, comparison: each needs what came before it) or the runs between two of them,
    each run's steps in order (training before its evaluation), the runs independent of each other."""
    groups: list[list[list[Step]]] = []
    runs: dict[tuple[str, ...], list[Step]] = {}
    for step in steps:
        run = run_of(step)
        if run is None:
            if runs:
                groups.append(list(runs.values()))
                runs = {}
            groups.append([[step]])
        else:
            runs.setdefault(run, []).append(step)
    if runs:
        groups.append(list(runs.values()))
    return groups


def run_group(runs: list[list[Step]], progress: StudyProgress, parallel: int) -> None:
    """Each run's steps in order, up to ``parallel`` runs at once (each with cores // parallel torch threads).
    After a failure no further run starts; the ones under way finish their step, then the failure is raised."""
    threads = max(1, (os.cpu_count() or 1) // parallel) if parallel > 1 else None
    failed = threading.Event()

    def run_steps(run: list[Step]) -> None:
        for step in run:
            if failed.is_set():
                return
            progress.start(step)
            try:
                info = run_step(step, progress, threads)
            except BaseException:
                failed.set()
                raise
            progress.write(f"[{step.key}] done in {info['seconds']:.0f} s")
            progress.finish(step)

    if parallel == 1 or len(runs) == 1:
        for run in runs:
            run_steps(run)
        return
    with ThreadPoolExecutor(min(parallel, len(runs))) as pool:
        futures = [pool.submit(run_steps, run) for run in runs]
        errors = [future.exception() for future in futures]
    for error in errors:
        if error is not None:
            raise error


def run_study(cfg: StudyConfig) -> Path:
    validate(cfg)
    out = output_dir(cfg)
    out.mkdir(parents=True, exist_ok=True)
    (out / "study.json").write_text(json.dumps(draccus.encode(cfg), indent=2, default=str))
    steps = plan(cfg)
    done = [s.done() for s in steps]
    progress = StudyProgress(cfg, steps, done)
    left = sum(e for e, d in zip(progress.estimates, done, strict=True) if not d)
    progress.write(
        f"jept-study {cfg.name}: {len(steps)} steps, {sum(done)} already done, about {left / 3600:.1f} h of "
        f"work left (estimated from the finished steps), outputs in {out}"
    )
    start = time.perf_counter()
    with progress.bar:
        todo = [step for step, finished in zip(steps, done, strict=True) if not finished]
        for group in step_groups(todo):
            run_group(group, progress, cfg.parallel)
    report = write_report(cfg)
    print(f"\nStudy finished in {time.perf_counter() - start:.0f} s (this run). Report: {report}")
    return report


# ---------------------------------------------------------------------------------------------------------
# The random 7-bin floor.


def random_floor(cfg: StudyConfig, split: SplitSpec) -> dict:
    """The random 7-bin policy's success per task of the split (:func:`lerobot_jept.evaluation.suite.random_floor`) on the
    suite's evaluation seeds, under the build's protocol."""
    from lerobot_jept.evaluation.suite import random_floor as floor_of
    from lerobot_jept.evaluation.suite import read_build_metadata

    build, _ = read_build_metadata(f"{split.repo_id}_mix", None)
    tasks = [*split.demo_tasks, *split.video_tasks, *split.unseen_tasks]
    per_task = floor_of(build, tasks, cfg.random_episodes, cfg.eval_seed, cfg.eval_episode_length)
    return {"episodes": cfg.random_episodes, "per_task": per_task}


# ---------------------------------------------------------------------------------------------------------
# The report.


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


def probe_table(cfg: StudyConfig, split: SplitSpec) -> tuple[str, dict]:
    """The offline probe per split group, mean [95% interval] over seeds, per method."""
    out = output_dir(cfg)
    values: dict[str, dict[str, dict[str, list[float]]]] = {}
    for method in cfg.methods:
        for seed in cfg.seeds:
            path = run_folder(out, split, method, seed) / "suite/results.json"
            if not path.is_file():
                continue
            probe = json.loads(path.read_text()).get("prompt_probe") or {}
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
    episodes = f"{cfg.eval_episodes} evaluation episodes per task and seed" + (
        f" ({', '.join(own)})" if own else ""
    )
    lines = [
        f"# Study `{cfg.name}` ({cfg.simulator})",
        "",
        f"Methods: {', '.join(m.name for m in cfg.methods)}; training seeds {cfg.seeds}, {cfg.steps} steps each; "
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
    if cfg.test is not None:
        text, verdict = preregistered_test(cfg)
        (out / "test.json").write_text(json.dumps(verdict, indent=2))
        lines += text
    report = out / "report.md"
    report.write_text("\n".join(lines))
    return report


def case_successes(cfg: StudyConfig, split: SplitSpec, method: str, task: str) -> tuple[list, list]:
    """Per training seed with a finished suite: the task's success % with its own prompt, and under the
    scene-mate's prompt (when the suite ran it)."""
    spec = next(m for m in cfg.methods if m.name == method)
    own, mate = [], []
    for seed in cfg.seeds:
        path = run_folder(output_dir(cfg), split, spec, seed) / "suite/results.json"
        if not path.is_file():
            continue
        row = json.loads(path.read_text())["per_task"].get(task)
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
        floor_path = out / slug(split.name) / "random_floor.done.json"
        floor = json.loads(floor_path.read_text())["per_task"] if floor_path.is_file() else {}
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


def main(args: list[str] | None = None) -> None:
    logging.basicConfig(level=logging.WARNING)
    args = list(sys.argv[1:] if args is None else args)
    config_path = None
    for i, arg in enumerate(args):
        if arg.startswith("--config="):
            config_path = args.pop(i).split("=", 1)[1]
            break
    if config_path is not None and not Path(config_path).is_file():
        sys.exit(f"jept-study: --config={config_path} does not exist (studies ship in examples/studies/).")
    cfg = draccus.parse(StudyConfig, config_path=config_path, args=args)
    try:
        run_study(cfg)
    except StudyError as err:
        sys.exit(f"jept-study: {err}")
