"""The baselines (``jept_dt_star``, ``jept_vid2robot``, ``jept_idm`` + ``jept-relabel``, ``jept_lapo``) and ``jept-compare``, on the
real tiny Meta-World build: what each objective sees, save/reload, and the LeRobot entry points."""

import json
import math
import shutil

import numpy as np
import pytest
import torch
from lerobot.policies.factory import make_policy, make_pre_post_processors

from lerobot_jept import DTStarConfig, DTStarPolicy, IDMConfig, IDMPolicy, LAPOConfig, Vid2RobotConfig
from lerobot_jept.evaluation.compare import CompareConfig, CompareError, compare
from lerobot_jept.evaluation.paper import PAPER_SPLIT
from lerobot_jept.policies.components.token_groups import DT_STAR_RULES, TokenGroup, attention_mask
from lerobot_jept.policies.jept.modeling_jept import IGNORE_INDEX
from tests.conftest import load
from tests.lerobot_jept.policies.test_policy import mixed_batch
from tests.lerobot_jept.test_end_to_end import MIX, PROMPTS, lerobot_eval, run

NO_DROPOUT = dict(frame_perceiver_dropout=0.0, prompt_perceiver_dropout=0.0, predictor_dropout=0.0)


def build(tiny_build, config_cls, **overrides):
    """A baseline in the small configuration at the tiny build's 64 px, with its preprocessed mixed batch."""
    from lerobot.datasets.lerobot_dataset import LeRobotDatasetMetadata

    torch.manual_seed(0)
    fields = {
        "device": "cpu",
        "image_size": 64,
        "max_prompt_length": 4,
        "prompt_repo_id": PROMPTS,
        **NO_DROPOUT,
    }
    cfg = config_cls.small(**{**fields, **overrides})
    meta = LeRobotDatasetMetadata(MIX)
    policy = make_policy(cfg, ds_meta=meta)
    pre, _ = make_pre_post_processors(cfg, dataset_stats=meta.stats)
    torch.manual_seed(0)
    return policy, pre(mixed_batch(cfg))


@pytest.fixture(scope="module")
def dt_star(tiny_build):
    return build(tiny_build, DTStarConfig)


@pytest.fixture(scope="module")
def vid2robot(tiny_build):
    return build(tiny_build, Vid2RobotConfig)


def test_dt_star_has_no_observation_prediction(dt_star):
    policy, batch = dt_star
    assert isinstance(policy, DTStarPolicy)
    names = {name for name, _ in policy.named_modules()}
    assert not {n for n in names if any(w in n for w in ("obs_head", "target", "emb_in", "temporal"))}
    k = policy.config.n_obs_steps
    assert batch["observation.image"].shape[1] == k  # the context only: no next frame to predict
    policy.eval()
    loss, info = policy.forward(batch)
    assert set(info) == {"loss_act", "labelled_fraction"}
    # the loss is L_act alone: cross-entropy of the bins on labelled frames, averaged per labelled sample
    m = policy.model
    logits = m.action_logits(
        m.encode_prompt(batch["observation.prompt_video"], None),
        m.frame_tokens(batch["observation.image"], batch["observation.state"]),
    )
    labels = batch["action"].clone()
    labels[batch["action_is_pad"]] = IGNORE_INDEX
    labels[(labels == IGNORE_INDEX).any(-1)] = IGNORE_INDEX
    ce = torch.nn.functional.cross_entropy(
        logits.permute(0, 3, 1, 2), labels, ignore_index=IGNORE_INDEX, reduction="none"
    )
    ok = (labels != IGNORE_INDEX).float()
    per_sample = (ce * ok).sum((1, 2)) / ok.sum((1, 2)).clamp_min(1)
    has = ok.sum((1, 2)) > 0
    assert loss.item() == pytest.approx(per_sample[has].mean().item(), rel=1e-5)


def test_dt_star_rules_are_block_causal_and_never_see_joint_embeddings(dt_star):
    groups = [TokenGroup("prompt", 2), TokenGroup("obs", 3), TokenGroup("emb", 3), TokenGroup("obs", 3)]
    blocked = attention_mask(groups, DT_STAR_RULES)
    assert blocked[:, 5:8].all()  # nobody attends to an emb group
    assert (
        not blocked[8:, 2:5].any() and blocked[2:5, 8:].all()
    )  # later obs see earlier obs, never the reverse
    policy, batch = dt_star
    m = policy.model.eval()
    prompt = m.encode_prompt(batch["observation.prompt_video"], None)
    obs = m.frame_tokens(batch["observation.image"], batch["observation.state"])
    changed = obs.clone()
    changed[:, -1] += torch.randn_like(changed[:, -1])
    before, after = m.transformer(prompt, obs), m.transformer(prompt, changed)
    torch.testing.assert_close(before[:, :-1], after[:, :-1])
    assert not torch.allclose(before[:, -1], after[:, -1])


def test_vid2robot_clones_only_labelled_frames_and_aligns_every_frame(tiny_build, vid2robot):
    """The BC loss gives no gradient to the unlabelled samples' frames; the auxiliary losses do. (In eval mode:
    in train mode the ResNet's batch norm couples every sample of a batch.)"""
    policy, batch = vid2robot
    policy.eval()
    labels = batch["action"]
    unlabelled = ((labels == IGNORE_INDEX).any(-1) | batch["action_is_pad"]).all(-1)  # (B,) no label at all
    assert unlabelled.any() and (~unlabelled).any()
    cfg = policy.config

    def image_grad(weight: float) -> tuple[torch.Tensor, dict]:
        cfg.video_contrastive_weight = cfg.video_alignment_weight = weight
        images = batch["observation.image"].clone().requires_grad_(True)
        loss, info = policy.forward({**batch, "observation.image": images})
        (grad,) = torch.autograd.grad(loss, images)
        return grad.abs().flatten(1).sum(-1), info

    try:
        bc_grad, _ = image_grad(0.0)  # behaviour cloning alone
        assert (bc_grad[unlabelled] == 0).all() and (bc_grad[~unlabelled] > 0).all()
        all_grad, info = image_grad(1.0)  # + the auxiliary losses
        assert (all_grad[unlabelled] > 0).all()
        assert info["loss_video_contrastive"] > 0 and info["loss_video_alignment"] > 0
    finally:
        cfg.video_contrastive_weight = cfg.video_alignment_weight = 1.0


def test_vid2robot_shares_one_perceiver_for_prompt_and_robot(vid2robot):
    policy, _ = vid2robot
    m = policy.model
    assert m.prompt_encoder.frame_perceiver is m.tokenizer.perceiver
    groups = policy.get_optim_params()
    ids = [id(p) for g in groups for p in g["params"]]
    assert len(ids) == len(set(ids)) == sum(p.requires_grad for p in policy.parameters())


@pytest.mark.parametrize("config_cls", [DTStarConfig, Vid2RobotConfig, IDMConfig, LAPOConfig])
def test_save_and_reload_give_identical_outputs(tiny_build, tmp_path, config_cls):
    policy, batch = build(tiny_build, config_cls)
    policy.eval()
    loss, _ = policy.forward(batch)
    policy.save_pretrained(tmp_path)
    reloaded = type(policy).from_pretrained(tmp_path).eval()
    assert reloaded.config.type == policy.config.type
    again, _ = reloaded.forward(batch)
    assert loss.item() == again.item()
    if config_cls is not IDMConfig:  # control: the same action from the same first observation
        obs = {k: v[:, -1] for k, v in batch.items() if k in ("observation.image", "observation.state")}
        obs |= {
            k: batch[k] for k in ("observation.prompt_video", "observation.prompt_video_mask") if k in batch
        }
        policy.reset(), reloaded.reset()
        torch.testing.assert_close(policy.select_action(obs), reloaded.select_action(obs))


def test_idm_learns_from_transitions_and_cannot_act(tiny_build):
    policy, batch = build(tiny_build, IDMConfig)
    assert isinstance(policy, IDMPolicy)
    assert batch["observation.image"].shape[1] == 2 and "observation.prompt_video" not in batch
    loss, info = policy.forward(batch)
    assert torch.isfinite(loss) and info["labelled_fraction"] > 0
    assert policy.action_logits(batch).shape == (8, 4, 7)
    with pytest.raises(NotImplementedError, match="jept-relabel"):
        policy.select_action(batch)


@pytest.mark.parametrize("config_cls", [DTStarConfig, Vid2RobotConfig, IDMConfig, LAPOConfig])
def test_small_configs_share_jepts_sizes(config_cls):
    """The shipped small configurations are ``Config.small()`` and use jept's sizes wherever they overlap."""
    from tests.lerobot_jept.test_end_to_end import CONFIG

    jept = json.loads(CONFIG.read_text())["policy"]
    name = config_cls.small().type
    mine = json.loads(CONFIG.with_name(f"train_{name.removeprefix('jept_')}_small_cpu.json").read_text())[
        "policy"
    ]
    assert mine["type"] == name
    assert {k: v for k, v in mine.items() if k != "type"} == {k: jept[k] for k in mine if k != "type"}
    small = config_cls.small()
    assert all(getattr(small, k) == v for k, v in mine.items() if k not in ("type", "device", "push_to_hub"))


# jept-compare ----------------------------------------------------------------------------------------------


def suite_output(folder, split, successes: dict[str, list[bool]], simulator="metaworld"):
    """A results.json as jept-eval-suite writes it, from per-episode outcomes."""
    from lerobot_jept.evaluation.suite import summarise

    rate = {t: 100.0 * sum(s) / len(s) for t, s in successes.items()}
    per_task = {
        t: {
            "split": next(r for r, ts in split.items() if t in ts),
            "pc_success": rate[t],
            "n_episodes": len(s),
            "successes": s,
        }
        for t, s in successes.items()
    }
    folder.mkdir(parents=True)
    results = {"simulator": simulator, "split": split, "per_task": per_task, "table": summarise(split, rate)}
    (folder / "results.json").write_text(json.dumps(results))
    return str(folder)


def test_compare_means_and_intervals(tmp_path):
    split = {"demo": ["a"], "video": ["b"], "unseen": ["c"]}
    # method X, three seeds: task a succeeds on 1, 2, 3 of 10 episodes -> T_demo 10, 20, 30; task c on 5, 6, 7
    # -> 50, 60, 70
    x = [
        suite_output(
            tmp_path / f"x{i}",
            split,
            {
                "a": [True] * i + [False] * (10 - i),
                "b": [True] * 10,
                "c": [True] * (4 + i) + [False] * (6 - i),
            },
        )
        for i in (1, 2, 3)
    ]
    y = [suite_output(tmp_path / "y", split, {"a": [True, False] * 5, "b": [False] * 10, "c": [True] * 10})]
    result = compare(CompareConfig(runs={"X": x, "Y": y}, output_dir=tmp_path / "out"))
    cell = result["table"]["X"]["T_demo"]
    half = 4.302652729911275 * 10 / math.sqrt(3)  # t(0.975, 2) * sd / sqrt(n)
    assert cell["mean"] == pytest.approx(20) and cell["seeds"] == [10, 20, 30]
    assert (cell["low"], cell["high"]) == (0, pytest.approx(20 + half))  # 20 - 24.8 clipped to 0
    unseen = result["table"]["X"]["c"]  # 50, 60, 70: the same half-width, not clipped
    assert (unseen["low"], unseen["high"]) == (pytest.approx(60 - half), pytest.approx(60 + half))
    vid = result["table"]["X"]["T_vid"]  # no spread between seeds: a zero-width interval
    assert (vid["mean"], vid["low"], vid["high"]) == (100, 100, 100)
    assert result["table"]["X"]["Seen average"]["mean"] == pytest.approx(
        60
    )  # mean of T_demo 20 and T_vid 100
    one = result["table"]["Y"]["T_demo"]  # one seed: bootstrap over its 10 episodes
    assert one["mean"] == 50 and 10 <= one["low"] < 50 < one["high"] <= 90 and "bootstrap" in one["interval"]
    assert result["table"]["Y"]["c"]["low"] == result["table"]["Y"]["c"]["high"] == 100
    assert result["paper"] is None  # not the paper's split
    text = (tmp_path / "out/comparison.md").read_text()
    assert "| T_demo | 20.0 [" in text and "| X | Y |" in text
    assert (tmp_path / "out/comparison.png").stat().st_size > 1000
    assert json.loads((tmp_path / "out/comparison.json").read_text())["table"]["X"]["T_demo"]["mean"] == 20


def test_compare_shows_the_paper_columns_on_the_paper_split(tmp_path):
    split = {k: list(v) for k, v in PAPER_SPLIT.items()}
    outcomes = {t: [True, False] for ts in split.values() for t in ts}
    runs = {
        "JEPT": [suite_output(tmp_path / "j", split, outcomes)],
        "DT*": [suite_output(tmp_path / "d", split, outcomes)],
    }
    result = compare(CompareConfig(runs=runs, output_dir=tmp_path / "out"))
    assert result["paper"]["JEPT"]["T_vid"] == 31.7 and result["paper"]["DT*"]["Unseen average"] == 1.5
    assert "JEPT (paper)" in (tmp_path / "out/comparison.md").read_text()


def test_compare_names_jept_columns_by_recipe_and_leaves_rows_a_method_did_not_run(tmp_path):
    split = {k: list(v) for k, v in PAPER_SPLIT.items()}
    outcomes = {t: [True, False] for ts in split.values() for t in ts}
    folders = {}
    for name, recipe in (("plus", "plus"), ("paper", "paper"), ("named", "plus")):
        folders[name] = suite_output(tmp_path / name, split, outcomes)
        results = json.loads((tmp_path / name / "results.json").read_text())
        results["recipe"] = recipe
        if name == "plus":  # this one also ran the video-only tasks under their scene-mates' prompts
            for task in split["video"]:
                results["per_task"][task]["scene_mate"] = {
                    "pc_success": 10.0,
                    "successes": [True] + [False] * 9,
                }
            results["table"]["T_vid, scene-mate's prompt"] = 10.0
        (tmp_path / name / "results.json").write_text(json.dumps(results))
    runs = {"JEPT": [folders["plus"]], "JEPT ": [folders["paper"]], "JEPT (plus), tuned": [folders["named"]]}
    result = compare(CompareConfig(runs=runs, output_dir=tmp_path / "out"))
    assert list(result["table"]) == ["JEPT (plus)", "JEPT  (paper)", "JEPT (plus), tuned"]
    assert result["paper"]["JEPT (plus)"]["T_vid"] == 31.7  # the paper's JEPT column still found
    row = "T_vid, scene-mate's prompt"
    assert (
        result["table"]["JEPT (plus)"][row]["mean"] == 10.0
        and not result["table"]["JEPT  (paper)"][row]["seeds"]
    )
    assert f"| {row} | 10.0 [" in (tmp_path / "out/comparison.md").read_text()


def test_compare_refuses_mismatched_or_old_outputs(tmp_path):
    a = suite_output(tmp_path / "a", {"demo": ["a"], "video": [], "unseen": []}, {"a": [True]})
    b = suite_output(tmp_path / "b", {"demo": ["b"], "video": [], "unseen": []}, {"b": [True]})
    with pytest.raises(CompareError, match="another split"):
        compare(CompareConfig(runs={"A": [a], "B": [b]}, output_dir=tmp_path / "out"))
    old = json.loads((tmp_path / "a/results.json").read_text())
    del old["per_task"]["a"]["successes"]
    (tmp_path / "a/results.json").write_text(json.dumps(old))
    with pytest.raises(CompareError, match="re-run jept-eval-suite"):
        compare(CompareConfig(runs={"A": [a]}, output_dir=tmp_path / "out"))


# LeRobot entry points ---------------------------------------------------------------------------------------


def train(tmp, policy_type: str, repo: str, steps: int = 2, *extra: str):
    from tests.lerobot_jept.test_end_to_end import CONFIG, TINY_TRAIN

    out = tmp / f"train_{policy_type}_{repo.split('/')[-1]}"
    config = CONFIG.with_name(f"train_{policy_type}_small_cpu.json")
    prompt = [] if policy_type == "idm" else [f"--policy.prompt_repo_id={PROMPTS}"]
    tiny = [a for a in TINY_TRAIN if not (policy_type == "idm" and "prompt" in a)]
    log = run(
        [
            "lerobot-train",
            f"--config_path={config}",
            f"--dataset.repo_id={repo}",
            *prompt,
            f"--steps={steps}",
            f"--save_freq={steps}",
            f"--output_dir={out}",
            "--policy.image_size=64",
            *tiny,
            *extra,
        ],
        tmp,
    )
    return out / "checkpoints/last/pretrained_model", log


@pytest.mark.slow
@pytest.mark.parametrize("policy_type", ["dt_star", "vid2robot", "lapo"])
def test_baseline_trains_and_evaluates_with_lerobot(tiny_build, tmp_path, policy_type):
    model, log = train(tmp_path, policy_type, MIX)
    assert json.loads((model / "config.json").read_text())["type"] == f"jept_{policy_type}"
    assert "loss_act:" in log and "loss_obs" not in log
    assert lerobot_eval(model, tmp_path / "eval", tmp_path)["overall"]["n_episodes"] == 1
    run(
        [
            "jept-eval-suite",
            f"--policy.path={model}",
            f"--dataset.repo_id={MIX}",
            "--n_episodes=2",
            "--batch_size=2",
            f"--output_dir={tmp_path / 'suite'}",
        ],
        tmp_path,
    )
    results = json.loads((tmp_path / "suite/results.json").read_text())
    assert results["policy_type"] == f"jept_{policy_type}"
    assert all(len(r["successes"]) == 2 for r in results["per_task"].values())
    probe = results["prompt_probe"]  # the baselines' offline measures: control only (no inverse, no L_obs)
    assert probe["policy_type"] == f"jept_{policy_type}" and set(probe["splits"]) == {
        "T_demo",
        "T_vid",
        "T_unseen",
    }
    assert all("control_whole" in r and "inverse_whole" not in r for r in probe["actions"].values())


@pytest.mark.slow
def test_idm_relabels_exactly_the_unlabelled_frames(tiny_build, tmp_path):
    from lerobot.datasets.lerobot_dataset import LeRobotDataset

    model, _ = train(tmp_path, "idm", MIX, 2, "--dataset.episodes=[0,1,2,3,4]")
    out = "test/mw_tiny_mix_idm"
    log = run(
        ["jept-relabel", f"--policy.path={model}", f"--dataset.repo_id={MIX}", f"--output_repo_id={out}"],
        tmp_path,
    )
    assert "Relabelled" in log
    source, relabelled = load(MIX), load(out)
    before = np.stack(source.hf_dataset.with_format("numpy")["action"])
    after = np.stack(relabelled.hf_dataset.with_format("numpy")["action"])
    pseudo = np.asarray(relabelled.hf_dataset.with_format("numpy")["pseudo_label"]).reshape(-1)
    marker = "observation.action_labelled"
    unlabelled = np.asarray(source.hf_dataset.with_format("numpy")[marker]).reshape(-1) == 0
    assert (np.asarray(relabelled.hf_dataset.with_format("numpy")[marker]) == 1).all()
    assert unlabelled.any() and (pseudo == unlabelled).all()
    assert before[~unlabelled].tobytes() == after[~unlabelled].tobytes()  # labelled frames untouched
    assert (
        np.isfinite(after).all()
        and np.isclose(after[unlabelled][..., None], np.linspace(-1, 1, 7), atol=1e-6).any(-1).all()
    )
    assert np.isfinite(relabelled.meta.stats["action"]["mean"]).all()
    record = json.loads((relabelled.root / "meta/jept_relabel.json").read_text())
    assert record["idm_checkpoint"] == str(model) and record["pseudo_labelled_frames"] == int(
        unlabelled.sum()
    )
    assert (
        record["idm_accuracy"]["frames"] == "heldout_episodes" and 0 <= record["idm_accuracy"]["whole"] <= 1
    )
    assert all(torch.isfinite(relabelled[i]["action"]).all() for i in range(len(relabelled)))  # loads in full
    assert (relabelled.root / "meta/jept_build.json").is_file()
    # LeRobot's own tools keep it whole (the relabelled repo is an ordinary one)
    run(
        [
            "lerobot-edit-dataset",
            f"--repo_id={out}",
            "--new_repo_id=test/idm_edited",
            "--operation.type=delete_episodes",
            "--operation.episode_indices=[0]",
        ],
        tmp_path,
    )
    edited = load("test/idm_edited")
    assert edited.meta.total_episodes == relabelled.meta.total_episodes - 1
    assert all(torch.isfinite(edited[i]["action"]).all() for i in range(len(edited)))
    assert isinstance(LeRobotDataset(out), LeRobotDataset)
    # BC = dt_star on the relabelled repo: every frame is labelled now
    _, log = train(tmp_path, "dt_star", out, 2, "--log_freq=1")
    fractions = {float(p.split(":")[1]) for p in log.split() if p.startswith("labelled_fraction:")}
    assert fractions == {1.0}
    again = run(
        ["jept-relabel", f"--policy.path={model}", f"--dataset.repo_id={MIX}", f"--output_repo_id={out}"],
        tmp_path,
        ok=False,
    )
    assert "already exists" in again


def test_jept_without_its_prompt_acts_the_same_under_any_prompt(tiny_build, tmp_path):
    """jept_no_prompt: the recipe's losses, one learned E_prt for every sample (trained in the prompt group),
    so another task's prompt video changes nothing; the prompt options are refused; save and reload act alike."""
    from lerobot_jept import JEPTNoPromptConfig, JEPTNoPromptPolicy
    from lerobot_jept.policies.jept.modeling_jept import PROMPT_VIDEO

    policy, batch = build(tiny_build, JEPTNoPromptConfig, phase_schedule="joint", temporal_dropout=0.0)
    cfg = policy.config
    assert (cfg.type, cfg.recipe, cfg.idm_input) == ("jept_no_prompt", "plus", "self_state")
    assert cfg.prompt_align_weight == cfg.prompt_swap_weight == cfg.prompt_guidance == 0.0
    policy.train()
    policy.num_updates.fill_(
        cfg.prompt_warmup_steps
    )  # past the warm-up: the constant stands in for the prompt
    loss, info = policy.forward(batch)
    loss.backward()
    assert info["prompt_on"] == 1.0 and "loss_prompt_swap" not in info
    assert policy.model.null_prompt.tokens.grad.abs().sum() > 0
    assert all(p.grad is None for p in policy.model.prompt_encoder.parameters())
    groups = {g["name"]: g["params"] for g in policy.get_optim_params()}
    assert any(p is policy.model.null_prompt.tokens for p in groups["prompt"])

    policy.eval()
    swapped = {**batch, PROMPT_VIDEO: batch[PROMPT_VIDEO].flip(0)}  # each sample shown another's prompt
    torch.testing.assert_close(
        policy.offline_outputs(swapped)["control"], policy.offline_outputs(batch)["control"]
    )
    policy.save_pretrained(tmp_path)
    reloaded = JEPTNoPromptPolicy.from_pretrained(tmp_path).eval()
    torch.testing.assert_close(
        reloaded.offline_outputs(batch)["control"], policy.offline_outputs(batch)["control"]
    )
    with pytest.raises(ValueError, match="jept_no_prompt has no prompt for --policy.prompt_swap_weight"):
        JEPTNoPromptConfig(prompt_swap_weight=1.0)


def test_self_state_idm_reads_the_state_change_alone_and_fits_it(tiny_build, tmp_path):
    """jept_idm with idm_input=self_state: no camera model at all, the logits depend on (s_t, s_t+1) only, and a
    few hundred steps on the tiny build's labelled transitions fit them; save and reload agree."""
    policy, batch = build(tiny_build, IDMConfig, idm_input="self_state")
    assert not hasattr(policy.model, "backbone") and policy.model.state_dynamics is not None
    other_frames = {**batch, "observation.image": torch.rand_like(batch["observation.image"])}
    policy.eval()
    torch.testing.assert_close(policy.action_logits(other_frames), policy.action_logits(batch))
    policy.train()
    optimizer = torch.optim.Adam(policy.parameters(), lr=3e-3)
    first = None
    for _ in range(200):
        loss, _ = policy.forward(batch)
        first = first if first is not None else loss.item()
        optimizer.zero_grad()
        loss.backward()
        optimizer.step()
    assert loss.item() < 0.3 * first
    policy.eval()
    policy.save_pretrained(tmp_path)
    reloaded = IDMPolicy.from_pretrained(tmp_path).eval()
    torch.testing.assert_close(reloaded.action_logits(batch), policy.action_logits(batch))


@pytest.mark.parametrize(
    "config_cls, option, value",
    [
        (DTStarConfig, "ema_decay", 0.5),
        (Vid2RobotConfig, "prompt_warmup_steps", 7),
        (LAPOConfig, "temporal_layers", 5),
        (IDMConfig, "phase_steps", 3),
    ],
)
def test_jept_options_are_no_options_of_a_baseline_and_its_older_checkpoints_still_load(
    tiny_build, tmp_path, config_cls, option, value
):
    import draccus
    from lerobot.configs.policies import PreTrainedConfig
    from lerobot.datasets.lerobot_dataset import LeRobotDatasetMetadata

    with pytest.raises(TypeError, match=option):
        config_cls(**{option: value})
    with pytest.raises(SystemExit):  # LeRobot's parser: an unknown argument
        draccus.parse(config_cls, args=[f"--{option}={value}"])
    meta = LeRobotDatasetMetadata(MIX)
    policy = make_policy(config_cls.small(device="cpu", image_size=64, prompt_repo_id=PROMPTS), ds_meta=meta)
    policy.save_pretrained(tmp_path / "new")
    saved = json.loads((tmp_path / "new/config.json").read_text())
    assert option not in saved and "recipe" not in saved
    # A checkpoint saved when the baselines carried JEPT's options: its config holds them.
    old = tmp_path / "old"
    shutil.copytree(tmp_path / "new", old)
    (old / "config.json").write_text(json.dumps({**saved, option: value, "recipe": "paper"}))
    loaded = type(policy).from_pretrained(old)
    assert loaded.config == policy.config  # the old keys are read and take no part
    for name, tensor in policy.state_dict().items():
        assert torch.equal(loaded.state_dict()[name], tensor), name
    # ... and so does a training run's config on resume (LeRobot decodes it as a choice of policy type).
    resumed = draccus.decode(PreTrainedConfig, {**saved, option: value})
    assert type(resumed) is config_cls
    loaded.save_pretrained(tmp_path / "again")
    assert option not in json.loads((tmp_path / "again/config.json").read_text())
