"""Hub round trips without the internet.

Download side, for real: a local `olah` server on 127.0.0.1 serves the tiny build and a checkpoint from git
repos through the Hub's download API; LeRobot and the plugin load them by repo id (HF_ENDPOINT) in fresh
processes with empty caches. Upload side: LeRobot's own push code runs against a recording stand-in of
`HfApi`, and the test checks the exact files, cards and tags it would send.
"""

import json
import os
import shutil
import socket
import subprocess
import sys
import time
import urllib.request
from pathlib import Path
from types import SimpleNamespace

import pytest
import torch
from huggingface_hub.utils import filter_repo_objects

from dataset_builders.core import BuildError, BuildPaths, push_repos
from tests.conftest import load
from tests.lerobot_jept.policies.test_policy import MIX, PROMPTS, build_policy

ROOT = Path(__file__).parents[2]
BIN = Path(sys.executable).parent
MODEL = "test/jept-tiny"


def git_repo(src: Path, dst: Path, tags: tuple[str, ...] = ()) -> None:
    shutil.copytree(src, dst)
    git = ["git", "-C", str(dst), "-c", "user.name=test", "-c", "user.email=test@example.com"]
    subprocess.run([*git, "init", "-q", "-b", "main"], check=True)
    subprocess.run([*git, "add", "-A"], check=True)
    subprocess.run([*git, "commit", "-q", "-m", "upload"], check=True)
    for tag in tags:
        subprocess.run([*git, "tag", tag], check=True)


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


@pytest.fixture(scope="module")
def checkpoint(tiny_build, tmp_path_factory) -> Path:
    policy, pre, post = build_policy(tiny_build)
    path = tmp_path_factory.mktemp("ckpt") / "pretrained_model"
    policy.save_pretrained(path)
    pre.save_pretrained(path)
    post.save_pretrained(path)
    return path


@pytest.fixture(scope="module")
def hub(tiny_build, checkpoint, tmp_path_factory):
    """An olah server on loopback serving the tiny build's mix and prompt bank and the checkpoint."""
    tmp = tmp_path_factory.mktemp("hub")
    home = Path(os.environ["HF_LEROBOT_HOME"])
    for repo in (MIX, PROMPTS):
        git_repo(home / repo, tmp / "mirrors/datasets" / repo, tags=("v3.0",))
    git_repo(checkpoint, tmp / "mirrors/models" / MODEL)
    port = free_port()
    config = tmp / "olah.toml"
    config.write_text(
        f'[basic]\nhost = "127.0.0.1"\nport = {port}\nmirrors-path = ["{tmp / "mirrors"}"]\n'
        f'repos-path = "{tmp / "repos"}"\nmirror-netloc = "127.0.0.1:{port}"\n'
        f'mirror-lfs-netloc = "127.0.0.1:{port}"\n\n[accessibility]\noffline = true\n'
    )
    server = subprocess.Popen(  # olah writes ./logs: run it in the test's folder
        [str(BIN / "olah-cli"), "-c", str(config)],
        cwd=tmp,
        stdout=subprocess.DEVNULL,
        stderr=subprocess.DEVNULL,
    )
    endpoint = f"http://127.0.0.1:{port}"
    try:
        deadline = time.monotonic() + 60
        while True:
            try:
                with urllib.request.urlopen(f"{endpoint}/api/datasets/{MIX}/revision/main", timeout=2) as r:
                    if r.status == 200:
                        break
            except OSError:
                pass
            assert server.poll() is None and time.monotonic() < deadline, "olah did not start"
            time.sleep(0.5)
        yield endpoint
    finally:
        server.terminate()
        server.wait(timeout=30)


def hub_env(endpoint: str, tmp: Path) -> dict:
    """A process that knows nothing locally: empty LeRobot and HF caches, the Hub at ``endpoint``."""
    return {
        **os.environ,
        "HF_ENDPOINT": endpoint,
        "HF_HUB_OFFLINE": "0",
        "HF_LEROBOT_HOME": str(tmp / "lerobot_home"),
        "HF_HOME": str(tmp / "hf_home"),
    }


def run(args: list[str], env: dict, cwd: Path) -> str:
    proc = subprocess.run(args, env=env, cwd=cwd, capture_output=True, text=True, timeout=900)
    assert proc.returncode == 0, f"{args[:2]} failed:\n{proc.stdout[-2000:]}\n{proc.stderr[-4000:]}"
    return proc.stdout


LOAD_BY_REPO_ID = f"""
import math, torch
import lerobot_policy_jept  # registers jept
from lerobot.datasets.lerobot_dataset import LeRobotDataset
from lerobot.policies.factory import make_pre_post_processors
from lerobot_jept import JEPTPolicy

ds = LeRobotDataset("{MIX}")
labelled = torch.stack(list(ds.hf_dataset["observation.action_labelled"]))
print("episodes", ds.num_episodes, "unlabelled_frames", int((labelled == 0).sum()))
policy = JEPTPolicy.from_pretrained("{MODEL}")
pre, post = make_pre_post_processors(policy.config, pretrained_path="{MODEL}")
frame = ds[0]
obs = {{"observation.image": frame["observation.image"], "observation.state": frame["observation.state"],
        "task": "Press a handle down"}}  # an unseen task: its prompt comes from the bank, by repo id
action = post(policy.select_action(pre(obs)))
print("action", tuple(action.shape))
"""


def test_datasets_policy_and_prompt_bank_load_by_repo_id(hub, tmp_path):
    out = run([sys.executable, "-c", LOAD_BY_REPO_ID], hub_env(hub, tmp_path), tmp_path)
    local = load(MIX)
    unlabelled = int((torch.stack(list(local.hf_dataset["observation.action_labelled"])) == 0).sum())
    assert f"episodes {local.num_episodes} unlabelled_frames {unlabelled}" in out and unlabelled > 0
    assert "action (1, 4)" in out
    assert (tmp_path / "lerobot_home/hub").exists()  # fetched, not found locally


@pytest.mark.slow
def test_lerobot_train_eval_and_own_loop_from_repo_ids(hub, tmp_path):
    env = hub_env(hub, tmp_path)
    run(
        [
            str(BIN / "lerobot-train"),
            f"--config_path={ROOT / 'examples/configs/train_jept_small_cpu.json'}",
            f"--dataset.repo_id={MIX}",
            f"--policy.prompt_repo_id={PROMPTS}",
            "--policy.max_prompt_length=4",
            "--policy.prompt_warmup_steps=0",
            "--steps=2",
            "--batch_size=2",
            "--num_workers=0",
            f"--output_dir={tmp_path / 'train'}",
        ],
        env,
        tmp_path,
    )
    assert (tmp_path / "train/checkpoints/last/pretrained_model/model.safetensors").is_file()
    run(
        [
            str(BIN / "lerobot-eval"),
            f"--policy.path={MODEL}",
            "--env.type=jept_metaworld",
            "--env.task=handle-press-v3",
            "--env.image_size=64",
            "--env.episode_length=10",
            f"--env.prompt_repo_id={PROMPTS}",
            "--env.prompt_max_frames=4",
            "--eval.n_episodes=1",
            "--eval.batch_size=1",
            "--policy.device=cpu",
            f"--output_dir={tmp_path / 'eval'}",
        ],
        env,
        tmp_path,
    )
    assert json.loads((tmp_path / "eval/eval_info.json").read_text())["overall"]["n_episodes"] == 1
    out = run(
        [
            sys.executable,
            str(ROOT / "examples/use_in_your_own_loop.py"),
            f"--policy_path={MODEL}",
            "--task=handle-press-v3",
            f"--prompt_repo_id={PROMPTS}",
            "--image_size=64",
        ],
        env,
        tmp_path,
    )
    assert out.strip() in ("handle-press-v3: success", "handle-press-v3: failure")


class RecordingHfApi:
    """Stands in for `huggingface_hub.HfApi`: records what would be sent, sends nothing."""

    calls: list = []
    fail: Exception | None = None

    def __init__(self, *args, **kwargs):
        pass

    def _record(self, name, **kwargs):
        if RecordingHfApi.fail is not None:
            raise RecordingHfApi.fail
        RecordingHfApi.calls.append((name, kwargs))

    def create_repo(self, repo_id, **kwargs):
        self._record("create_repo", repo_id=repo_id, **kwargs)
        return SimpleNamespace(repo_id=repo_id)

    def create_branch(self, repo_id, **kwargs):
        self._record("create_branch", repo_id=repo_id, **kwargs)

    def create_tag(self, repo_id, **kwargs):
        self._record("create_tag", repo_id=repo_id, **kwargs)

    def delete_tag(self, repo_id, **kwargs):
        self._record("delete_tag", repo_id=repo_id, **kwargs)

    def upload_folder(self, *, repo_id, folder_path, allow_patterns=None, ignore_patterns=None, **kwargs):
        root = Path(folder_path)
        files = sorted(str(p.relative_to(root)) for p in root.rglob("*") if p.is_file())
        files = sorted(
            filter_repo_objects(files, allow_patterns=allow_patterns, ignore_patterns=ignore_patterns)
        )
        contents = {f: (root / f).read_text() for f in files if f.endswith((".md", ".json"))}
        self._record("upload_folder", repo_id=repo_id, files=files, contents=contents, **kwargs)
        return SimpleNamespace(repo_url=SimpleNamespace(url=f"https://huggingface.co/{repo_id}"))

    upload_large_folder = upload_folder


@pytest.fixture
def recording_hub(monkeypatch):
    import huggingface_hub.repocard
    import lerobot.datasets.lerobot_dataset
    import lerobot.policies.pretrained
    import lerobot.utils.hub

    RecordingHfApi.calls, RecordingHfApi.fail = [], None
    for module in (lerobot.datasets.lerobot_dataset, lerobot.policies.pretrained, lerobot.utils.hub):
        monkeypatch.setattr(module, "HfApi", RecordingHfApi)

    def upload_file(*, path_or_fileobj, path_in_repo, repo_id, **kwargs):
        text = (
            path_or_fileobj.decode()
            if isinstance(path_or_fileobj, bytes)
            else Path(path_or_fileobj).read_text()
        )
        RecordingHfApi()._record("upload_file", repo_id=repo_id, path=path_in_repo, text=text)

    monkeypatch.setattr(huggingface_hub.repocard, "upload_file", upload_file)
    # Card validation is a request to the Hub's YAML validator: not reachable here.
    monkeypatch.setattr(huggingface_hub.repocard.RepoCard, "validate", lambda self, repo_type=None: None)
    return RecordingHfApi


def build_metadata(tiny_build) -> tuple[BuildPaths, dict]:
    cfg, _ = tiny_build
    paths = BuildPaths(cfg)
    return paths, json.loads((paths.repo("mix") / "meta/jept_build.json").read_text())


def test_builder_push_sends_every_repo_with_cards_and_tags(tiny_build, recording_hub):
    paths, metadata = build_metadata(tiny_build)
    push_repos(paths, metadata)
    calls = recording_hub.calls
    created = [kw["repo_id"] for name, kw in calls if name == "create_repo"]
    assert created == [f"test/mw_tiny_{r}" for r in ("demo", "video", "prompts", "probe", "mix")]
    uploads = {kw["repo_id"]: kw for name, kw in calls if name == "upload_folder"}
    for repo, upload in uploads.items():
        files = upload["files"]
        local = paths.repo(repo.rsplit("_", 1)[1])
        assert files == sorted(str(p.relative_to(local)) for p in local.rglob("*") if p.is_file())  # exactly
        meta = {"meta/info.json", "meta/stats.json", "meta/jept_build.json", "meta/tasks.parquet"}
        assert meta <= set(files)
        assert any(f.startswith("data/") and f.endswith(".parquet") for f in files)
        assert any(f.startswith("videos/") and f.endswith(".mp4") for f in files), repo
    assert "action" not in json.loads(uploads["test/mw_tiny_video"]["contents"]["meta/info.json"])["features"]
    tags = {kw["repo_id"]: kw["tag"] for name, kw in calls if name == "create_tag"}
    assert set(tags.values()) == {"v3.0"} and len(tags) == 5
    cards = {
        kw["repo_id"]: kw["text"] for name, kw in calls if name == "upload_file" and kw["path"] == "README.md"
    }
    assert len(cards) == 5
    for role in ("demo", "video", "prompts", "probe", "mix"):
        card = cards[f"test/mw_tiny_{role}"]
        assert "- T_demo: button-press-v3, reach-v3" in card and "- T_unseen: handle-press-v3" in card
        assert "image_size 64" in card and "action_bins 7" in card and "action_repeat 2" in card
        assert "max_episode_steps 250" in card and "corner2" in card
        assert "button-press-v3 100%" in card
        assert f"- {role}" in card and "- jept" in card and "- metaworld" in card  # card tags
    assert "no `action` column by design" in cards["test/mw_tiny_video"]
    assert "never trained on" in cards["test/mw_tiny_probe"]


def test_failed_builder_push_is_one_line_and_keeps_files(tiny_build, recording_hub):
    paths, metadata = build_metadata(tiny_build)
    before = sorted(p.relative_to(paths.repo("mix")) for p in paths.repo("mix").rglob("*"))
    recording_hub.fail = ConnectionError("Network is unreachable\nmore detail")
    with pytest.raises(BuildError) as err:
        push_repos(paths, metadata)
    message = str(err.value)
    assert (
        "\n" not in message and "Network is unreachable" in message and "re-run the same command" in message
    )
    assert sorted(p.relative_to(paths.repo("mix")) for p in paths.repo("mix").rglob("*")) == before
    assert load(MIX).num_episodes == 9


def train_config(policy, tmp_path):
    from lerobot.configs.default import DatasetConfig
    from lerobot.configs.train import TrainPipelineConfig

    policy.config.repo_id = MODEL
    return TrainPipelineConfig(dataset=DatasetConfig(repo_id=MIX), policy=policy.config, output_dir=tmp_path)


def test_policy_push_sends_safetensors_processors_and_a_jept_card(tiny_build, recording_hub, tmp_path):
    from lerobot.datasets.lerobot_dataset import LeRobotDatasetMetadata

    policy, pre, post = build_policy(tiny_build)
    cfg = train_config(policy, tmp_path)
    policy.push_model_to_hub(cfg, dataset_meta=LeRobotDatasetMetadata(MIX))
    pre.push_to_hub(MODEL)
    post.push_to_hub(MODEL)
    uploads = [kw for name, kw in recording_hub.calls if name == "upload_folder"]
    assert uploads[0]["files"] == ["README.md", "config.json", "model.safetensors", "train_config.json"]
    processor_files = set(uploads[1]["files"]) | set(uploads[2]["files"])
    assert {"policy_preprocessor.json", "policy_postprocessor.json"} <= processor_files
    assert all(f.endswith((".json", ".safetensors")) for f in processor_files)  # no pickle anywhere
    card = uploads[0]["contents"]["README.md"]
    for text in (
        f"Training data: `{MIX}`",
        f"Prompt bank: `{PROMPTS}`",
        "- T_vid: drawer-close-v3",
        f"lerobot-eval --policy.path={MODEL} --env.type=jept_metaworld",
        "jept-eval-suite",
    ):
        assert text in card, text
    config = json.loads(uploads[0]["contents"]["config.json"])
    assert config["type"] == "jept" and config["prompt_repo_id"] == PROMPTS


def test_failed_policy_push_is_one_line(tiny_build, recording_hub, tmp_path):
    policy, _, _ = build_policy(tiny_build)
    recording_hub.fail = PermissionError("401 Unauthorized: invalid token")
    with pytest.raises(SystemExit) as err:
        policy.push_model_to_hub(train_config(policy, tmp_path))
    assert "\n" not in str(err.value.code) and "401 Unauthorized" in str(err.value.code)


def test_checkpoint_loads_only_safetensors_and_checks_the_plugin_version(checkpoint, monkeypatch, tmp_path):
    from lerobot_jept import JEPTPolicy

    assert not [p for p in checkpoint.iterdir() if p.suffix in (".bin", ".pt", ".pth", ".pkl")]

    def no_pickle(*args, **kwargs):
        raise AssertionError("torch.load (pickle) called while loading a checkpoint")

    monkeypatch.setattr(torch, "load", no_pickle)
    JEPTPolicy.from_pretrained(checkpoint)
    old = tmp_path / "old"
    shutil.copytree(checkpoint, old)
    config = json.loads((old / "config.json").read_text())
    (old / "config.json").write_text(json.dumps({**config, "plugin_version": "7.0.0"}))
    with pytest.raises(ValueError, match=r"saved by lerobot_policy_jept 7.0.0.*lerobot_policy_jept==7\.\*"):
        JEPTPolicy.from_pretrained(old)
