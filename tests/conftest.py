"""The tests' environment: offline Hub, headless rendering, and a private LeRobot home.

These must be set before LeRobot or MuJoCo are imported, hence at the top of conftest.
"""

import os
import tempfile

os.environ["HF_HUB_OFFLINE"] = "1"
os.environ.setdefault("MUJOCO_GL", "egl")
os.environ.setdefault("SVT_LOG", "1")
os.environ["HF_LEROBOT_HOME"] = tempfile.mkdtemp(prefix="jept_lerobot_home_")
if (
    "PYTEST_XDIST_WORKER_COUNT" in os.environ
):  # `pytest -n N`: share the cores instead of each taking them all
    threads = str(max(1, (os.cpu_count() or 1) // int(os.environ["PYTEST_XDIST_WORKER_COUNT"])))
    for name in ("OMP_NUM_THREADS", "MKL_NUM_THREADS"):  # read by torch at import, inherited by subprocesses
        os.environ.setdefault(name, threads)

import pytest  # noqa: E402

from dataset_builders.core import build  # noqa: E402
from dataset_builders.metaworld import MetaworldBuildConfig, MetaworldSimulator  # noqa: E402

SIM = MetaworldSimulator()
TINY = dict(
    demo_tasks=["button-press-v3", "reach-v3"],
    video_tasks=["drawer-close-v3"],
    unseen_tasks=["handle-press-v3"],
    episodes_per_task=3,
    prompts_per_task=2,
    probe_episodes_per_task=1,
    image_size=64,
    episodes_per_shard=2,
)


def load(repo_id: str, **kwargs):
    from lerobot.datasets.lerobot_dataset import LeRobotDataset

    return LeRobotDataset(repo_id, **kwargs)  # found under $HF_LEROBOT_HOME, as lerobot-train finds it


def write_clip(frames, path, fps: int = 20) -> None:
    """(N, 3, H, W) uint8 frames -> an MPEG-4 file, as a user's camera would give one."""
    import av

    with av.open(str(path), "w") as container:
        stream = container.add_stream("mpeg4", rate=fps)
        stream.height, stream.width = frames.shape[-2:]
        stream.pix_fmt = "yuv420p"
        stream.options = {"qscale": "1"}
        for frame in frames.permute(0, 2, 3, 1).numpy():
            container.mux(stream.encode(av.VideoFrame.from_ndarray(frame, format="rgb24")))
        container.mux(stream.encode())


@pytest.fixture(scope="session")
def tiny_build():
    """A real tiny Meta-World build, ``test/mw_tiny_{demo,video,prompts,probe,mix}``, shared by all tests."""
    cfg = MetaworldBuildConfig(repo_id="test/mw_tiny", **TINY)
    summary = build(cfg, SIM)
    return cfg, summary
