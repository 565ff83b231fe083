"""The simulator-independent core of the JEPT dataset builders.

A build turns expert rollouts into four LeRobotDataset v3 repos under ``$HF_LEROBOT_HOME``:

- ``<repo_id>_demo``: T_demo episodes with ``action`` (the bin centre the env executed) and
  ``observation.action_labelled`` = 1;
- ``<repo_id>_video``: T_vid episodes with the same observation features and NO ``action`` feature;
- ``<repo_id>_prompts``: the prompt-video bank, ``prompts_per_task`` observation-only episodes of every task;
- ``<repo_id>_probe``: ``probe_episodes_per_task`` held-out labelled episodes (with ``action``) of every task of
  every split, for offline measures of a checkpoint (``jept-prompt-probe``); never used for training;
- ``<repo_id>_mix``: demo + video episodes in the one repo ``lerobot-train`` needs; video frames have
  ``observation.action_labelled`` = 0 and the neutral action 0, and ``meta/stats.json`` action stats come from
  labelled frames only (``lerobot_jept.mixing``: a representation LeRobot's dataset tools keep whole).

How it stays resumable and safe to kill. Work is cut into *shards* (up to ``episodes_per_shard`` successful
episodes of one task and one role). A shard is recorded as its own small LeRobotDataset in a ``.tmp`` folder
of the build's work directory (``<repo_id>.build/``) and renamed into place only once finalised, so a shard is
either complete or absent. Re-running the same command skips complete shards. The repos are assembled from
the shards with LeRobot's ``aggregate_datasets`` into a temporary folder that then replaces the repo by a
rename: a repo is always absent or complete, never half written. Each shard draws its episode seeds from
its own range, so the episodes do not depend on the number of workers or on interruptions.

Processes. Each recording process (the build's own, or each of ``num_workers`` pool workers) starts one
rollout process (:class:`Renderer`, spawned: a fresh GL context) that owns the env and runs up to
``ROLLOUTS_AHEAD`` episodes ahead, while the recording process writes the current one with LeRobot's writer.
Results come back in submission order, so a build's episodes do not depend on this overlap either.

A simulator plugs in through :class:`Simulator` (env factory, task names, features); everything else lives
here, once.
"""

import abc
import atexit
import json
import logging
import multiprocessing as mp
import os
import queue
import shutil
import threading
import time
from collections import defaultdict
from concurrent.futures import FIRST_COMPLETED, ProcessPoolExecutor, wait
from dataclasses import asdict, dataclass, field
from pathlib import Path

from lerobot_jept.discretization import snap_to_bins
from lerobot_jept.mixing import MIX_FORMAT

ROLES = ("demo", "video", "prompts", "probe")
LABELLED_ROLES = ("demo", "probe")  # recorded with the executed action
ROLLOUTS_AHEAD = 2  # episodes the rollout process may run ahead of the writing
SPLITS = ("demo", "video", "unseen")
BUILD_FILE = "jept_build.json"  # written in <work dir>/ and in every repo's meta/
# Episode seeds: each (role, shard) owns a disjoint block of SEED_BLOCK seeds, so training episodes and
# prompt videos and probe episodes never share a seed, and all stay clear of lerobot-eval's default seeds (1000 + episode).
SEED_BLOCK = 10_000
ROLE_SEED_BASE = {"demo": 10_000_000, "video": 10_000_000, "prompts": 20_000_000, "probe": 30_000_000}
# Flags added after builds were made: a build recorded without one takes the value given now (its shards are
# recorded on top of the existing ones), so an older build resumes with today's defaults.
ADDED_FLAGS = ("probe_episodes_per_task",)
# Flags that change what is written; a repo built with other values is never mixed with new episodes.
CONTENT_FLAGS = (
    "demo_tasks",
    "video_tasks",
    "unseen_tasks",
    "episodes_per_task",
    "prompts_per_task",
    "probe_episodes_per_task",
    "image_size",
    "seed",
    "action_bins",
    "action_repeat",
    "max_episode_steps",
    "episodes_per_shard",
    "vcodec",
)

logger = logging.getLogger(__name__)


class BuildError(ValueError):
    """A build request that cannot be carried out; the message says how to fix it."""


@dataclass
class BuildConfig:
    """Flags shared by every ``jept-build-*`` command (the simulator's config sets the defaults).

    Attributes:
        repo_id: ``ORG/NAME``; the build writes ``ORG/NAME_demo``, ``_video``, ``_prompts`` and ``_mix``.
        demo_tasks: T_demo, tasks recorded with actions.
        video_tasks: T_vid, tasks recorded as expert videos without actions.
        unseen_tasks: T_unseen, tasks that only get prompt videos.
        episodes_per_task: successful expert episodes per demo/video task.
        prompts_per_task: prompt videos per task (all three splits), seeds disjoint from training episodes.
        probe_episodes_per_task: held-out labelled episodes per task (all three splits) in ``<repo_id>_probe``,
            seeds disjoint from every other role; 0 for none.
        image_size: side of the square camera image.
        seed: base seed; the same flags and seed give the same episodes.
        num_workers: parallel rollout processes (one simulator env per process).
        action_bins: bins per action dimension; experts execute the nearest bin centre.
        action_repeat: simulator steps per recorded step.
        max_episode_steps: recorded steps before an episode is truncated (and rejected as a failure).
        episodes_per_shard: unit of work and of resumption.
        vcodec: video codec of the camera stream (``h264`` at the ``veryfast`` preset costs a fifth of the CPU
            time of LeRobot's default ``libsvtav1``, which matters when rendering on a CPU; ``libsvtav1`` gives
            smaller files).
        root: folder holding the repos; default ``$HF_LEROBOT_HOME`` (where LeRobot looks for ``repo_id``).
        push_to_hub: push every repo with LeRobot's ``push_to_hub`` at the end.
        private: create the Hub repos as private.
    """

    repo_id: str = "local/jept"
    demo_tasks: list[str] = field(default_factory=list)
    video_tasks: list[str] = field(default_factory=list)
    unseen_tasks: list[str] = field(default_factory=list)
    episodes_per_task: int = 500
    prompts_per_task: int = 10
    probe_episodes_per_task: int = 4
    image_size: int = 224
    seed: int = 0
    num_workers: int = 1
    action_bins: int = 7
    action_repeat: int = 2
    max_episode_steps: int = 250
    episodes_per_shard: int = 25
    vcodec: str = "h264"
    root: str | None = None
    push_to_hub: bool = False
    private: bool = False

    def split(self) -> dict[str, list[str]]:
        return {
            "demo": list(self.demo_tasks),
            "video": list(self.video_tasks),
            "unseen": list(self.unseen_tasks),
        }

    def content_flags(self) -> dict:
        return {name: getattr(self, name) for name in CONTENT_FLAGS}


class Simulator(abc.ABC):
    """What a simulator module provides to the core. Instances must be picklable (they go to workers)."""

    name: str  # e.g. "metaworld"
    robot_type: str

    @abc.abstractmethod
    def check_task(self, task: str) -> str:
        """Return ``task`` or raise :class:`BuildError` listing close matches."""

    @abc.abstractmethod
    def task_description(self, task: str) -> str:
        """The task string written to the datasets; equal to the eval env's ``task_description``."""

    @abc.abstractmethod
    def make_env(self, task: str, cfg: BuildConfig, role: str = "demo"):
        """A gymnasium env with ``{"pixels", "agent_pos"}`` observations and an ``expert_action()`` method.
        ``role`` is the repo being recorded (``"prompts"`` may show another embodiment than the others)."""

    @abc.abstractmethod
    def fps(self, cfg: BuildConfig) -> int:
        """Recorded frames per second."""

    @abc.abstractmethod
    def observation_features(self, cfg: BuildConfig) -> dict:
        """LeRobot features of the observation (``observation.image``, ``observation.state``)."""

    @abc.abstractmethod
    def action_feature(self) -> dict:
        """LeRobot feature of the executed action."""

    def protocol(self, cfg: BuildConfig) -> dict:
        """What a reader of the dataset card needs to reproduce the observations."""
        return {
            "simulator": self.name,
            "robot_type": self.robot_type,
            "image_size": cfg.image_size,
            "fps": self.fps(cfg),
            "action_bins": cfg.action_bins,
            "action_repeat": cfg.action_repeat,
            "max_episode_steps": cfg.max_episode_steps,
        }


@dataclass(frozen=True)
class Shard:
    """Up to ``episodes_per_shard`` successful episodes of one task for one role."""

    role: str
    task: str
    index: int
    num_episodes: int

    @property
    def name(self) -> str:
        return f"{self.role}/{self.task}/{self.index:04d}"

    def seed(self, base_seed: int, attempt: int) -> int:
        if attempt >= SEED_BLOCK:
            raise BuildError(f"Shard {self.name} needed more than {SEED_BLOCK} attempts.")
        return (base_seed * 1_000_003 + ROLE_SEED_BASE[self.role] + self.index * SEED_BLOCK + attempt) % 2**31


def validate(cfg: BuildConfig, sim: Simulator) -> None:
    """Reject bad flags before any work starts, with one sentence that names the fix."""
    if "/" not in cfg.repo_id or cfg.repo_id.count("/") != 1:
        raise BuildError(f"--repo_id must look like ORG/NAME, got {cfg.repo_id!r}.")
    for name in ("episodes_per_task", "prompts_per_task", "image_size", "num_workers", "episodes_per_shard"):
        if getattr(cfg, name) < 1:
            raise BuildError(f"--{name} must be at least 1, got {getattr(cfg, name)}.")
    if cfg.probe_episodes_per_task < 0:
        raise BuildError(f"--probe_episodes_per_task must be 0 or more, got {cfg.probe_episodes_per_task}.")
    if cfg.action_bins < 2:
        raise BuildError(f"--action_bins must be at least 2, got {cfg.action_bins}.")
    if cfg.action_repeat < 1 or cfg.max_episode_steps < 1:
        raise BuildError("--action_repeat and --max_episode_steps must be at least 1.")
    if not cfg.demo_tasks and not cfg.video_tasks:
        raise BuildError("Nothing to train on: give at least one task in --demo_tasks or --video_tasks.")
    seen: dict[str, str] = {}
    for split, tasks in cfg.split().items():
        for task in tasks:
            sim.check_task(task)
            if task in seen:
                where = "twice in" if seen[task] == split else f"in both {seen[task]}_tasks and"
                raise BuildError(f"Task {task!r} is {where} {split}_tasks: a task belongs to one split only.")
            seen[task] = split


def plan_shards(cfg: BuildConfig) -> list[Shard]:
    """Every shard of the build, in the order episodes appear in the repos."""
    jobs = [
        ("demo", cfg.demo_tasks, cfg.episodes_per_task),
        ("video", cfg.video_tasks, cfg.episodes_per_task),
    ]
    all_tasks = [*cfg.demo_tasks, *cfg.video_tasks, *cfg.unseen_tasks]
    jobs.append(("prompts", all_tasks, cfg.prompts_per_task))
    jobs.append(("probe", all_tasks, cfg.probe_episodes_per_task))
    shards = []
    for role, tasks, per_task in jobs:
        for task in tasks:
            for index, start in enumerate(range(0, per_task, cfg.episodes_per_shard)):
                shards.append(Shard(role, task, index, min(cfg.episodes_per_shard, per_task - start)))
    return shards


class BuildPaths:
    """Where a build writes: the repos under ``root`` and the shards in ``<repo_id>.build``."""

    def __init__(self, cfg: BuildConfig):
        from lerobot.utils.constants import HF_LEROBOT_HOME

        self.root = Path(cfg.root) if cfg.root else HF_LEROBOT_HOME
        self.repo_id = cfg.repo_id
        self.work = self.root / f"{cfg.repo_id}.build"

    def repo_id_of(self, role: str) -> str:
        return f"{self.repo_id}_{role}"

    def repo(self, role: str) -> Path:
        return self.root / self.repo_id_of(role)

    def shard(self, shard: Shard) -> Path:
        return self.work / "shards" / shard.name

    def shard_repo_id(self, shard: Shard) -> str:
        return f"{self.repo_id}.build_{shard.role}_{shard.task}_{shard.index:04d}"


# ---------------------------------------------------------------------------------------------------------
# Recording one shard (runs in a worker process, or in the main process when num_workers == 1).

_ENV_CACHE: dict = {}  # one live env per process: (simulator name, task, flags) -> env


def _env_for(sim: Simulator, task: str, cfg: BuildConfig, role: str):
    key = (sim.name, task, role, cfg.image_size, cfg.action_repeat, cfg.max_episode_steps)
    if key not in _ENV_CACHE:
        close_envs()
        _ENV_CACHE[key] = sim.make_env(task, cfg, role)
    return _ENV_CACHE[key]


def close_envs() -> None:
    """Close this process's cached env (frees its GL context before the GL library is unloaded)."""
    for env in _ENV_CACHE.values():
        env.close()
    _ENV_CACHE.clear()


def rollout_expert(env, seed: int, action_bins: int) -> tuple[list[dict], bool]:
    """One expert episode: frames ``{observation.image, observation.state, action}`` and whether it succeeded.

    The expert's continuous action is snapped to the nearest bin centre, which is what the env executes and
    what is recorded. The observation after the last action is not recorded (it has no action).
    """
    low, high = float(env.action_space.low.min()), float(env.action_space.high.max())
    obs, _ = env.reset(seed=seed)
    frames = []
    while True:
        action = snap_to_bins(env.expert_action(), action_bins, low, high)
        frames.append(
            {"observation.image": obs["pixels"], "observation.state": obs["agent_pos"], "action": action}
        )
        obs, _, terminated, truncated, info = env.step(action)
        if terminated or truncated:
            return frames, bool(info["is_success"])


def record_shard(sim: Simulator, cfg: BuildConfig, shard: Shard, progress) -> dict:
    """Record ``shard`` into its own finalised LeRobotDataset; returns its summary.

    ``progress(role, episodes, frames, rejected)`` is called after every attempted episode.
    """
    from lerobot.datasets.lerobot_dataset import LeRobotDataset

    quiet_writer()
    paths = BuildPaths(cfg)
    final = paths.shard(shard)
    tmp = final.with_name(final.name + ".tmp")
    shutil.rmtree(tmp, ignore_errors=True)
    with_actions = shard.role in LABELLED_ROLES
    features = dict(sim.observation_features(cfg))
    if with_actions:
        features["action"] = sim.action_feature()
    dataset = LeRobotDataset.create(
        repo_id=paths.shard_repo_id(shard),
        fps=sim.fps(cfg),
        features=features,
        root=tmp,
        robot_type=sim.robot_type,
        use_videos=True,
        streaming_encoding=True,
        rgb_encoder=encoder_config(cfg.vcodec),
        encoder_threads=1,
    )
    description = sim.task_description(shard.task)
    renderer = _renderer()
    kept, attempt, submitted, frames_total, seeds = 0, 0, 0, 0, []
    max_attempts = 20 * shard.num_episodes + 20

    def submit_ahead(needed: int) -> None:
        """Keep up to ROLLOUTS_AHEAD attempts in flight, never more than the episodes still ``needed``."""
        nonlocal submitted
        while submitted - attempt < min(ROLLOUTS_AHEAD, needed) and submitted < max_attempts:
            renderer.submit(sim, cfg, shard.task, shard.role, shard.seed(cfg.seed, submitted))
            submitted += 1

    # The rollout process rolls out the next episodes while this process writes the current one (stats,
    # parquet, video): two cores busy, where a writer thread would share the GIL with the rollout. Results
    # come back in submission order, so the episodes are those of a sequential build.
    try:
        submit_ahead(shard.num_episodes)
        while kept < shard.num_episodes:
            if submitted == attempt:
                raise BuildError(
                    f"The {shard.task} expert failed {attempt - kept} of {attempt} episodes; "
                    f"check the task or raise --max_episode_steps (now {cfg.max_episode_steps})."
                )
            frames, success = renderer.result()
            seed = shard.seed(cfg.seed, attempt)
            attempt += 1
            submit_ahead(shard.num_episodes - kept - success)
            if not success:
                progress(shard.role, 0, 0, 1)
                continue
            _write_episode(dataset, frames, description, with_actions)
            kept += 1
            frames_total += len(frames)
            seeds.append(seed)
            progress(shard.role, 1, len(frames), 0)
    except BaseException:
        close_renderer()  # it may hold rollouts of this shard that no one will read
        raise
    dataset.finalize()
    summary = {**asdict(shard), "attempts": attempt, "frames": frames_total, "seeds": seeds}
    (tmp / "shard.json").write_text(json.dumps(summary))
    final.parent.mkdir(parents=True, exist_ok=True)
    os.replace(tmp, final)
    return summary


def encoder_config(vcodec: str):
    from lerobot.configs.video import RGBEncoderConfig

    if vcodec == "h264":
        return RGBEncoderConfig(vcodec="h264", preset="veryfast")
    return RGBEncoderConfig(vcodec=vcodec)


def _write_episode(dataset, frames: list[dict], task: str, with_actions: bool) -> None:
    for frame in frames:
        if not with_actions:
            frame.pop("action")
        dataset.add_frame({**frame, "task": task})
    dataset.save_episode()


def quiet_writer() -> None:
    """Errors only from libav, also once LeRobot's encoder hands logging back to FFmpeg's own printer (which
    otherwise prints x264's banner and statistics for every episode); no `datasets` progress bar for the map
    that ``save_episode`` runs on every episode (the build has its own bars)."""
    import av
    from datasets.utils.logging import disable_progress_bar

    av.logging.set_level(av.logging.ERROR)
    av.logging.set_libav_level(av.logging.ERROR)
    disable_progress_bar()


class Renderer:
    """Expert rollouts in a child process that keeps the current task's env: :meth:`submit` one episode,
    :meth:`result` waits for it (errors raised in the child are raised here)."""

    def __init__(self):
        ctx = mp.get_context("spawn")  # a fresh process has no inherited GL context
        self._conn, child_conn = ctx.Pipe()
        self._process = ctx.Process(target=_render_loop, args=(child_conn,), daemon=True)
        self._process.start()
        child_conn.close()
        self._pending = 0

    def submit(self, sim: "Simulator", cfg: "BuildConfig", task: str, role: str, seed: int) -> None:
        self._conn.send((sim, cfg, task, role, seed))
        self._pending += 1

    def result(self) -> tuple[list[dict], bool]:
        try:
            ok, value = self._conn.recv()
            self._pending -= 1
        except (EOFError, ConnectionResetError):
            self._process.join(timeout=5)
            raise BuildError(
                f"The rollout process exited (exit code {self._process.exitcode}); see its messages above. "
                'A script that calls build() needs an `if __name__ == "__main__":` guard (the process is '
                "started with spawn, which imports the script)."
            ) from None
        if not ok:
            raise value
        return value

    def close(self) -> None:
        """Stop the process (at once when it is still rolling out an episode nobody will read)."""
        if self._process.is_alive() and not self._pending:
            self._conn.send(None)
            self._process.join(timeout=30)
        if self._process.is_alive():
            self._process.kill()
            self._process.join()
        self._conn.close()


def _render_loop(conn) -> None:
    worker_init()
    # Results are sent by a thread, so the next rollout starts while the parent is still busy writing.
    outbox: queue.Queue = queue.Queue()
    sender = threading.Thread(target=_send_results, args=(conn, outbox), daemon=True)
    sender.start()
    try:
        while (request := conn.recv()) is not None:
            sim, cfg, task, role, seed = request
            try:
                result = (True, rollout_expert(_env_for(sim, task, cfg, role), seed, cfg.action_bins))
            except Exception as err:  # handed to the parent, which raises it
                result = (False, err)
            outbox.put(result)
    except EOFError:
        pass  # the parent is gone (killed): nothing left to do
    finally:
        outbox.put(None)
        close_envs()


def _send_results(conn, outbox: queue.Queue) -> None:
    try:
        while (result := outbox.get()) is not None:
            conn.send(result)
    except (BrokenPipeError, ConnectionResetError):
        pass  # the parent is gone


_RENDERER: list[Renderer] = []


def _renderer() -> Renderer:
    """This process's renderer, started on first use."""
    if not _RENDERER:
        _RENDERER.append(Renderer())
    return _RENDERER[0]


def close_renderer() -> None:
    while _RENDERER:
        _RENDERER.pop().close()


def _record_in_worker(sim, cfg, shard, progress_queue) -> dict:
    def progress(role, episodes, frames, rejected):
        progress_queue.put((role, episodes, frames, rejected))

    return record_shard(sim, cfg, shard, progress)


def worker_init() -> None:
    # One render/physics thread per process: the processes are the parallelism.
    os.environ.setdefault("LP_NUM_THREADS", "1")
    import torch

    torch.set_num_threads(1)
    atexit.register(close_renderer)


class ProgressBars:
    """One tqdm bar per repo with episodes/s and frames/s."""

    def __init__(self, totals: dict[str, int], done: dict[str, int]):
        from tqdm.auto import tqdm

        self.start = time.perf_counter()
        self.frames = defaultdict(int)
        self.rejected = defaultdict(int)
        self.bars = {
            role: tqdm(total=total, initial=done.get(role, 0), desc=f"{role:>7}", unit="ep", position=i)
            for i, (role, total) in enumerate(totals.items())
        }

    def __call__(self, role: str, episodes: int, frames: int, rejected: int) -> None:
        self.frames[role] += frames
        self.rejected[role] += rejected
        bar = self.bars[role]
        bar.update(episodes)
        elapsed = max(time.perf_counter() - self.start, 1e-9)
        bar.set_postfix(frames_per_s=f"{self.frames[role] / elapsed:.1f}", rejected=self.rejected[role])

    def close(self) -> None:
        for bar in self.bars.values():
            bar.close()


def run_shards(sim: Simulator, cfg: BuildConfig, shards: list[Shard], progress) -> list[dict]:
    """Record ``shards`` with ``cfg.num_workers`` processes (in this process when it is 1)."""
    if cfg.num_workers == 1 or len(shards) <= 1:
        try:
            return [record_shard(sim, cfg, shard, progress) for shard in shards]
        finally:
            close_renderer()
    ctx = mp.get_context("spawn")  # a fresh process has no inherited GL context
    with ctx.Manager() as manager:
        progress_queue = manager.Queue()
        with ProcessPoolExecutor(cfg.num_workers, mp_context=ctx, initializer=worker_init) as pool:
            pending = {pool.submit(_record_in_worker, sim, cfg, shard, progress_queue) for shard in shards}
            results = []
            while pending:
                done, pending = wait(pending, timeout=0.2, return_when=FIRST_COMPLETED)
                results += [future.result() for future in done]
                try:
                    while True:
                        progress(*progress_queue.get_nowait())
                except queue.Empty:
                    pass
            return results


# ---------------------------------------------------------------------------------------------------------
# Assembling the repos from the shards.


def _replace_dir(tmp: Path, final: Path) -> None:
    """Swap ``tmp`` in as ``final`` by renames (the old version is removed only after the swap)."""
    old = final.with_name(final.name + ".old")
    shutil.rmtree(old, ignore_errors=True)
    if final.exists():
        os.replace(final, old)
    os.replace(tmp, final)
    shutil.rmtree(old, ignore_errors=True)


def _recover_dir(final: Path) -> None:
    """Undo a swap interrupted between its two renames (the previous complete version comes back)."""
    old = final.with_name(final.name + ".old")
    if old.exists() and not final.exists():
        os.replace(old, final)


def _with_labels(root: Path, repo_id: str) -> Path:
    """The assembled demo repo at ``root`` with ``observation.action_labelled`` = 1 on every frame."""
    from lerobot.datasets.lerobot_dataset import LeRobotDataset

    from lerobot_jept.mixing import add_labels

    out = root.with_name(root.name + "_labelled")
    add_labels(LeRobotDataset(repo_id, root=root), out, repo_id, labelled=True)
    shutil.rmtree(root)
    return out


def _aggregate(sources: list[tuple[str, Path]], repo_id: str, out: Path) -> None:
    from lerobot.datasets.aggregate import aggregate_datasets

    shutil.rmtree(out, ignore_errors=True)
    aggregate_datasets(
        repo_ids=[rid for rid, _ in sources],
        aggr_repo_id=repo_id,
        roots=[p for _, p in sources],
        aggr_root=out,
    )


def build_mix(paths: BuildPaths, action_feature: dict, has_demo: bool, has_video: bool) -> None:
    """``_mix`` = the ``_demo`` episodes + the ``_video`` episodes with the neutral action, unlabelled
    (``lerobot_jept.mixing``)."""
    from lerobot_jept.mixing import mix

    demos = [(paths.repo_id_of("demo"), paths.repo("demo"))] if has_demo else []
    videos = [(paths.repo_id_of("video"), paths.repo("video"))] if has_video else []
    staging = paths.work / "staging" / "mixing"
    try:
        done = mix(demos, videos, paths.repo_id_of("mix"), staging, action_feature)
    except ValueError as err:
        raise BuildError(str(err)) from err
    _replace_dir(done, paths.repo("mix"))
    shutil.rmtree(staging, ignore_errors=True)


def dir_size(path: Path) -> int:
    return sum(p.stat().st_size for p in path.rglob("*") if p.is_file())


def _check_existing(paths: BuildPaths, cfg: BuildConfig, sim: Simulator) -> dict | None:
    """The previous build record, after checking it was made with the same content flags."""
    record_path = paths.work / BUILD_FILE
    if not record_path.exists():
        existing = [paths.repo_id_of(r) for r in (*ROLES, "mix") if paths.repo(r).exists()]
        if existing:
            raise BuildError(
                f"{', '.join(existing)} already exist(s) under {paths.root} but were not built by this builder "
                f"(no {record_path}); choose another --repo_id or delete them."
            )
        return None
    record = json.loads(record_path.read_text())
    wanted = {"simulator": sim.name, **cfg.content_flags()}
    added = {name: wanted[name] for name in ADDED_FLAGS}
    previous = {"simulator": record.get("simulator"), **added, **record.get("flags", {})}
    changed = [f"--{k}={previous.get(k)!r} (now {v!r})" for k, v in wanted.items() if previous.get(k) != v]
    if changed:
        raise BuildError(
            f"{cfg.repo_id} was built with different flags: {'; '.join(changed)}. Re-run with the original "
            f"flags to resume it, use another --repo_id, or delete {paths.work} and the {cfg.repo_id}_* repos."
        )
    return record


def build(cfg: BuildConfig, sim: Simulator) -> dict:
    """Run a whole build (validate, record missing shards, assemble repos, write metadata); return summary."""
    from lerobot_jept.envs.rendering import setup_offscreen_gl

    validate(cfg, sim)
    setup_offscreen_gl()
    paths = BuildPaths(cfg)
    for role in (*ROLES, "mix"):
        _recover_dir(paths.repo(role))
    record = _check_existing(paths, cfg, sim) or {}
    paths.work.mkdir(parents=True, exist_ok=True)
    record.update({"simulator": sim.name, "flags": cfg.content_flags()})
    (paths.work / BUILD_FILE).write_text(json.dumps(record, indent=2))

    shards = plan_shards(cfg)
    todo = [s for s in shards if not paths.shard(s).exists()]
    totals = defaultdict(int)
    done = defaultdict(int)
    for s in shards:
        totals[s.role] += s.num_episodes
        if s not in todo:
            done[s.role] += s.num_episodes
    start = time.perf_counter()
    bars = ProgressBars(dict(totals), dict(done))
    try:
        run_shards(sim, cfg, todo, bars)
    finally:
        bars.close()
    record_seconds = time.perf_counter() - start

    summaries = [json.loads((paths.shard(s) / "shard.json").read_text()) for s in shards]
    assembled = record.get("assembled", {})
    if assembled.get("format") != MIX_FORMAT:  # repos assembled by an older version are assembled again
        assembled = {"format": MIX_FORMAT}
    for role in ROLES:
        role_shards = [s for s in shards if s.role == role]
        names = [s.name for s in role_shards]
        if not role_shards or (assembled.get(role) == names and paths.repo(role).exists()):
            continue
        tmp = paths.work / "staging" / role
        _aggregate(
            [(paths.shard_repo_id(s), paths.shard(s)) for s in role_shards], paths.repo_id_of(role), tmp
        )
        if role in LABELLED_ROLES:  # every frame labelled, as in the mix, so that LeRobot can merge them
            tmp = _with_labels(tmp, paths.repo_id_of(role))
        _replace_dir(tmp, paths.repo(role))
        assembled[role] = names
        assembled.pop("mix", None)
    mix_names = [s.name for s in shards if s.role in ("demo", "video")]
    if assembled.get("mix") != mix_names or not paths.repo("mix").exists():
        build_mix(paths, sim.action_feature(), bool(cfg.demo_tasks), bool(cfg.video_tasks))
        assembled["mix"] = mix_names
    record["assembled"] = assembled

    stats = _episode_stats(summaries)
    metadata = {
        "repo_id": cfg.repo_id,
        "split": cfg.split(),
        "task_descriptions": {t: sim.task_description(t) for tasks in cfg.split().values() for t in tasks},
        "protocol": sim.protocol(cfg),
        "repos": {role: paths.repo_id_of(role) for role in (*ROLES, "mix") if paths.repo(role).exists()},
        "expert_success_rate": {task: s["episodes"] / s["attempts"] for task, s in stats["per_task"].items()},
        "flags": cfg.content_flags(),
    }
    for role in metadata["repos"]:
        (paths.repo(role) / "meta" / BUILD_FILE).write_text(json.dumps(metadata, indent=2))
    record["metadata"] = metadata
    (paths.work / BUILD_FILE).write_text(json.dumps(record, indent=2))

    per_role = stats["per_role"]
    per_role["mix"] = {
        key: per_role["demo"][key] + per_role["video"][key] for key in ("episodes", "frames", "attempts")
    }
    summary = {
        "record_seconds": record_seconds,
        "total_seconds": time.perf_counter() - start,
        "repos": {
            role: {
                "repo_id": paths.repo_id_of(role),
                "path": str(paths.repo(role)),
                "episodes": per_role[role]["episodes"],
                "frames": per_role[role]["frames"],
                "rejected": per_role[role]["attempts"] - per_role[role]["episodes"],
                "bytes": dir_size(paths.repo(role)),
            }
            for role in metadata["repos"]
        },
        "expert_success_rate": metadata["expert_success_rate"],
    }
    print(format_summary(summary))
    if cfg.push_to_hub:
        push_repos(paths, metadata, private=cfg.private)
    return summary


def _episode_stats(summaries: list[dict]) -> dict:
    per_role = defaultdict(lambda: {"episodes": 0, "frames": 0, "attempts": 0})
    per_task = defaultdict(lambda: {"episodes": 0, "attempts": 0})
    for s in summaries:
        for bucket in (per_role[s["role"]], per_task[s["task"]]):
            bucket["episodes"] += s["num_episodes"]
            bucket["attempts"] += s["attempts"]
        per_role[s["role"]]["frames"] += s["frames"]
    return {"per_role": per_role, "per_task": per_task}


def format_summary(summary: dict) -> str:
    lines = [f"{'repo':<40} {'episodes':>9} {'frames':>9} {'rejected':>9} {'size MB':>9}"]
    for info in summary["repos"].values():
        lines.append(
            f"{info['repo_id']:<40} {info['episodes']:>9} {info['frames']:>9} {info['rejected']:>9} "
            f"{info['bytes'] / 1e6:>9.1f}"
        )
    rates = ", ".join(f"{t} {r:.0%}" for t, r in summary["expert_success_rate"].items())
    lines.append(f"expert success (kept / attempted): {rates}")
    lines.append(f"time: {summary['total_seconds']:.1f} s (recording {summary['record_seconds']:.1f} s)")
    return "\n".join(lines)


ROLE_DESCRIPTIONS = {
    "demo": "expert demonstrations (camera, self-state and the executed action) of the T_demo tasks",
    "video": (
        "expert videos of the T_vid tasks: camera and self-state only. This repo has no `action` column by "
        "design: JEPT learns these tasks from video alone"
    ),
    "prompts": "the prompt-video bank: observation-only episodes of every task, looked up by task string",
    "probe": (
        "held-out labelled episodes (camera, self-state and the executed action) of every task of every split, "
        "with seeds disjoint from all other repos: never trained on, they measure a checkpoint offline "
        "(`jept-prompt-probe`, `jept-eval-suite`)"
    ),
    "mix": (
        "the single training repo for `lerobot-train`: demo and video episodes together; video frames have "
        "`observation.action_labelled` = 0 and a neutral action of 0 (stats come from labelled frames only)"
    ),
}


def dataset_card_description(metadata: dict, role: str) -> str:
    """The card text of one repo: its role, the split, the protocol and the expert success rates."""
    split, protocol = metadata["split"], metadata["protocol"]
    lines = [
        f"JEPT {protocol['simulator']} build `{metadata['repo_id']}`, written by `lerobot_policy_jept`'s builder.",
        "",
        f"This repo (`{metadata['repos'][role]}`) holds {ROLE_DESCRIPTIONS[role]}.",
        "",
        "**Task split** (the paper's T_demo / T_vid / T_unseen):",
    ]
    for name, key in (("T_demo", "demo"), ("T_vid", "video"), ("T_unseen", "unseen")):
        lines.append(f"- {name}: {', '.join(split[key]) or '(none)'}")
    lines += [
        "",
        "**Protocol**: "
        + ", ".join(f"{k} {v}" for k, v in protocol.items())
        + " (camera `corner2`, flipped upright; actions are the centres of the bins the expert's actions were "
        "snapped to).",
        "",
        "**Expert success rates** (kept / attempted): "
        + ", ".join(f"{t} {r:.0%}" for t, r in metadata["expert_success_rate"].items()),
        "",
        "Repos of this build: "
        + ", ".join(f"`{r}`" for r in metadata["repos"].values())
        + ". The split and protocol are also in `meta/jept_build.json`.",
    ]
    return "\n".join(lines)


def push_repos(paths: BuildPaths, metadata: dict, private: bool = False) -> None:
    """Push every repo of the build with LeRobot's own ``push_to_hub``; a failure keeps every local file and
    ends in one line (BuildError)."""
    from lerobot.datasets.lerobot_dataset import LeRobotDataset

    for role, repo_id in metadata["repos"].items():
        dataset = LeRobotDataset(repo_id, root=paths.repo(role))
        try:
            dataset.push_to_hub(
                tags=["jept", metadata["protocol"]["simulator"], role],
                private=private,
                dataset_description=dataset_card_description(metadata, role),
            )
        except Exception as err:  # network, auth, permissions: whatever the Hub client raises
            reason = str(err).strip().splitlines()[0] if str(err).strip() else type(err).__name__
            raise BuildError(
                f"Pushing {repo_id} to the Hub failed ({type(err).__name__}: {reason}). Every repo is complete "
                f"locally under {paths.repo(role).parent}; log in (`hf auth login`) and re-run the same command "
                "to push again."
            ) from err
