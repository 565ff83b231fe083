"""``jept-study``: the paper's experiments as one resumable command.

    jept-study --config=examples/studies/cpu_small.json [--output_dir=DIR] [--device=cpu|cuda] [--parallel=2]
    jept-study --config=examples/studies/cpu_small.json --report_only=true   # the report from what has finished

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
import shlex
import subprocess
import sys
import threading
import time
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import draccus
import numpy as np
from tqdm import tqdm

from lerobot_jept.study.config import (
    StudyConfig,
    StudyError,
    method_named,
    method_steps,
    output_dir,
    start_step,
    validate,
)
from lerobot_jept.study.plan import Step, plan
from lerobot_jept.study.report import write_report

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
    """What a step's cost is estimated from: (method, kind) for a run's steps (its own method, also when it runs
    in another method's run), (kind,) for a split's."""
    parts = step.key.split("/")
    return (parts[1], parts[-1]) if run_of(step) else (parts[-1],)


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
    estimates = []
    for step, seconds in zip(steps, recorded, strict=True):
        if seconds is None:
            key = cost_key(step)
            known = seen.get(key) or seen.get(key[-1:])
            kind = key[-1]
            if known:
                seconds = float(np.mean(known))
            else:  # per training step (the steps this method's runs train), per episode and task, else per step
                units = cfg.eval_episodes * tasks if kind == "suite" else 1
                if kind in ("train", "idm"):
                    method = method_named(cfg, key[0])
                    units = method_steps(cfg, method) - start_step(cfg, method) if method else cfg.steps
                seconds = PRIOR_SECONDS.get(kind, 10.0) * units
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
        running = sum(min(now - since, 0.95 * self.estimates[i]) for i, since in self.running_since.items())
        # tqdm's ETA divides what is left by the progress made since the bar opened: steps that have only
        # just started would give it a speed near zero and an ETA of days; until they have run a second it
        # shows "?"
        self.bar.n = self.done_seconds() + (running if running >= 1.0 else 0.0)
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
    if step.run is not None:
        return step.run
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


def finished(step: Step, report_only: bool) -> bool:
    """:meth:`Step.done`; for the report alone a marker of another command only means the step has not run."""
    try:
        return step.done()
    except StudyError:
        if report_only:
            return False
        raise


def run_study(cfg: StudyConfig) -> Path:
    validate(cfg)
    out = output_dir(cfg)
    out.mkdir(parents=True, exist_ok=True)
    (out / "study.json").write_text(json.dumps(draccus.encode(cfg), indent=2, default=str))
    steps = plan(cfg)
    done = [finished(s, cfg.report_only) for s in steps]
    todo = [step for step, ran in zip(steps, done, strict=True) if not ran]
    if cfg.report_only:
        missing = [step.key for step in todo if not step.always]
        print(
            f"jept-study {cfg.name}: the report from {len(steps) - len(todo)} finished steps of {len(steps)}"
            + (f"; not run: {', '.join(missing)}" if missing else ""),
            flush=True,
        )
        steps = todo = [step for step in todo if step.always]  # the comparisons, over what has finished
        done = [False] * len(steps)
    progress = StudyProgress(cfg, steps, done)
    left = sum(e for e, d in zip(progress.estimates, done, strict=True) if not d)
    progress.write(
        f"jept-study {cfg.name}: {len(steps)} steps, {sum(done)} already done, about {left / 3600:.1f} h of "
        f"work left (estimated from the finished steps), outputs in {out}"
    )
    start = time.perf_counter()
    with progress.bar:
        for group in step_groups(todo):
            run_group(group, progress, cfg.parallel)
    report = write_report(cfg)
    print(f"\nStudy finished in {time.perf_counter() - start:.0f} s (this run). Report: {report}")
    return report


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
