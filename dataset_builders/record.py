"""Recording shards: expert rollouts in a rollout process per recording process, each shard written as its
own finalised LeRobotDataset (``record_shard``), and ``num_workers`` recording processes (``run_shards``).

Each recording process (the build's own, or each pool worker) starts one rollout process (:class:`Renderer`,
spawned: a fresh GL context) that owns the env and runs up to ``ROLLOUTS_AHEAD`` episodes ahead, while the
recording process writes the current one with LeRobot's writer. Results come back in submission order, so a
build's episodes do not depend on this overlap.
"""

import atexit
import ctypes
import json
import multiprocessing as mp
import os
import queue
import shutil
import signal
import sys
import threading
import time
from collections import defaultdict
from concurrent.futures import FIRST_COMPLETED, ProcessPoolExecutor, wait
from dataclasses import asdict
from multiprocessing.managers import SyncManager

import numpy as np

from dataset_builders.config import (
    LABELLED_ROLES,
    PLAY_HOLD_PROB,
    BuildConfig,
    BuildError,
    Simulator,
    is_play,
    scene_task,
    task_description,
)
from dataset_builders.plan import BuildPaths, Shard
from lerobot_jept.policies.discretization import bin_centres, snap_to_bins

ROLLOUTS_AHEAD = 2  # episodes the rollout process may run ahead of the writing
RANDOM_ACTION_STREAM = 7919  # keeps the random-action draws apart from the env's own use of the seed

_ENV_CACHE: dict = {}  # one live env per process: (simulator name, task, flags) -> env


def _env_for(sim: Simulator, task: str, cfg: BuildConfig, role: str):
    key = (sim.name, scene_task(task), role, cfg.image_size, cfg.action_repeat, cfg.max_episode_steps)
    if key not in _ENV_CACHE:
        close_envs()
        _ENV_CACHE[key] = sim.make_env(scene_task(task), cfg, role)
    return _ENV_CACHE[key]


def close_envs() -> None:
    """Close this process's cached env (frees its GL context before the GL library is unloaded)."""
    for env in _ENV_CACHE.values():
        env.close()
    _ENV_CACHE.clear()


def rollout_expert(env, seed: int, action_bins: int, random_prob: float = 0.0) -> tuple[list[dict], bool]:
    """One expert episode: frames ``{observation.image, observation.state, action}`` and whether it succeeded.

    The expert's continuous action is snapped to the nearest bin centre, which is what the env executes and
    what is recorded; with probability ``random_prob`` a step takes a uniformly random bin action instead (its
    draws come from ``seed``). The observation after the last action is not recorded (it has no action).
    """
    low, high = float(env.action_space.low.min()), float(env.action_space.high.max())
    centres = bin_centres(action_bins, low, high).astype(np.float32)
    rng = np.random.default_rng([seed, RANDOM_ACTION_STREAM])
    obs, _ = env.reset(seed=seed)
    frames = []
    while True:
        action = snap_to_bins(env.expert_action(), action_bins, low, high)
        if random_prob > 0 and rng.random() < random_prob:
            action = centres[rng.integers(action_bins, size=action.shape)]
        frames.append(
            {"observation.image": obs["pixels"], "observation.state": obs["agent_pos"], "action": action}
        )
        obs, _, terminated, truncated, info = env.step(action)
        if terminated or truncated:
            return frames, bool(info["is_success"])


def rollout_play(
    env, seed: int, action_bins: int, steps: int, policy: str = "random"
) -> tuple[list[dict], bool]:
    """One play episode of ``steps`` steps in ``env``'s scene, as :func:`rollout_expert` records it but without
    an expert, acting by ``policy`` (:data:`~dataset_builders.config.PLAY_POLICIES`). There is no task to
    succeed at: the episode goes on when the scene's task happens to succeed, and every episode is kept."""
    low, high = float(env.action_space.low.min()), float(env.action_space.high.max())
    rng = np.random.default_rng([seed, RANDOM_ACTION_STREAM])
    act = PLAYERS[policy](rng, action_bins, low, high)
    obs, _ = env.reset(seed=seed)
    frames = []
    while True:
        action = act(env)
        frames.append(
            {"observation.image": obs["pixels"], "observation.state": obs["agent_pos"], "action": action}
        )
        obs, *_ = env.step(action)
        if len(frames) == steps:
            return frames, True


class RandomPlay:
    """A uniformly random bin action, kept at each step with probability ``hold_prob`` (else drawn again)."""

    def __init__(self, rng, action_bins: int, low: float, high: float, hold_prob: float = PLAY_HOLD_PROB):
        self.rng, self.hold_prob, self.action = rng, hold_prob, None
        self.centres = bin_centres(action_bins, low, high).astype(np.float32)

    def __call__(self, env) -> np.ndarray:
        if self.action is None or self.rng.random() >= self.hold_prob:
            self.action = self.centres[self.rng.integers(len(self.centres), size=env.action_space.shape)]
        return self.action


class ReachPlay:
    """Object-centred play: the hand is driven to a random point within ``radius`` of the scene's object with
    a random gripper command (open or closed), at the gain of Meta-World's scripted experts, until it is within
    ``tolerance`` or ``max_steps`` have passed; then the next point. The actions are the experts' kind (mostly
    saturated moves towards a point), in every direction around the object, so they push and pull its handle
    both ways whatever the scene's task is."""

    gain, radius, tolerance, max_steps = 10.0, 0.15, 0.02, 30

    def __init__(self, rng, action_bins: int, low: float, high: float):
        self.rng, self.bins, self.low, self.high = rng, action_bins, low, high
        self.target, self.grip, self.left = None, 0.0, 0

    def __call__(self, env) -> np.ndarray:
        hand, obj = env.hand_and_object()
        if self.left == 0 or np.linalg.norm(self.target - hand) < self.tolerance:
            self.target = obj + self.rng.uniform(-self.radius, self.radius, size=3)
            self.grip, self.left = float(self.rng.choice([-1.0, 1.0])), self.max_steps
        self.left -= 1
        move = np.clip(self.gain * (self.target - hand), -1.0, 1.0)
        return snap_to_bins(np.append(move, self.grip), self.bins, self.low, self.high).astype(np.float32)


PLAYERS = {"random": RandomPlay, "reach": ReachPlay}  # PLAY_POLICIES' actors


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
    description = task_description(sim, shard.task)
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
                env = _env_for(sim, task, cfg, role)
                if is_play(task):
                    result = (
                        True,
                        rollout_play(env, seed, cfg.action_bins, cfg.max_episode_steps, cfg.play_policy),
                    )
                else:
                    result = (True, rollout_expert(env, seed, cfg.action_bins, cfg.expert_random_prob))
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


def die_with_parent() -> None:
    """On Linux, this process gets SIGTERM when the process that started it dies: a killed build leaves no worker
    behind still writing the shard its re-run records again."""
    if sys.platform.startswith("linux"):
        ctypes.CDLL(None, use_errno=True).prctl(1, signal.SIGTERM)  # 1: PR_SET_PDEATHSIG


def worker_init() -> None:
    die_with_parent()
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
    manager = SyncManager(ctx=ctx)
    manager.start(die_with_parent)
    with manager:
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


def record_missing(sim: Simulator, cfg: BuildConfig, paths: BuildPaths, shards: list[Shard]) -> float:
    """Record the shards of ``shards`` that are not on disk yet, with progress bars; returns the seconds."""
    todo = [s for s in shards if not paths.shard(s).exists()]
    totals, done = defaultdict(int), defaultdict(int)
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
    return time.perf_counter() - start
