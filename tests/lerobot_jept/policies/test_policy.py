"""The `jept` policy on a real tiny Meta-World build: losses, masking, EMA, phases, save/load, control cache."""

import copy
import dataclasses
import json
import sys

import pytest
import torch
from lerobot.configs.types import FeatureType, PolicyFeature
from lerobot.datasets.factory import resolve_delta_timestamps
from lerobot.policies.factory import make_policy, make_pre_post_processors
from lerobot.processor import PolicyProcessorPipeline
from safetensors.torch import load_file

from lerobot_jept import JEPTConfig, JEPTPolicy
from lerobot_jept.policies.base import frame_mean
from lerobot_jept.policies.jept.modeling_jept import IGNORE_INDEX, PROMPT_VIDEO
from lerobot_jept.policies.jept.processor_jept import JeptActionBinsStep
from lerobot_jept.policies.prompts import PromptNotFoundError
from tests.conftest import load, write_clip

MIX, PROMPTS = "test/mw_tiny_mix", "test/mw_tiny_prompts"


def tiny_config(config_cls=JEPTConfig, **overrides) -> JEPTConfig:
    """The small CPU configuration at the tiny build's 64 px, without dropout so outputs are deterministic."""
    fields = dict(
        device="cpu",
        image_size=64,
        max_prompt_length=4,
        prompt_repo_id=PROMPTS,
        frame_perceiver_dropout=0.0,
        prompt_perceiver_dropout=0.0,
        temporal_dropout=0.0,
        predictor_dropout=0.0,
        phase_schedule="joint",
        prompt_warmup_steps=0,
    )
    # JEPT's options are no options of a baseline.
    own = {f.name for f in dataclasses.fields(config_cls) if f.init}
    fields = {k: v for k, v in fields.items() if k in own}
    return config_cls.small(**{**fields, **overrides})


def build_policy(tiny_build, config_cls=JEPTConfig, **overrides):
    from lerobot.datasets.lerobot_dataset import LeRobotDatasetMetadata

    torch.manual_seed(0)
    cfg = tiny_config(config_cls, **overrides)
    meta = LeRobotDatasetMetadata(MIX)
    policy = make_policy(cfg, ds_meta=meta)
    pre, post = make_pre_post_processors(cfg, dataset_stats=meta.stats)
    return policy, pre, post


def mixed_batch(cfg, size=8, seed=0):
    """A batch with both demo frames (actions) and video frames (no actions), as lerobot-train samples it."""
    from lerobot.datasets.lerobot_dataset import LeRobotDatasetMetadata

    ds = load(MIX, delta_timestamps=resolve_delta_timestamps(cfg, LeRobotDatasetMetadata(MIX)))
    g = torch.Generator().manual_seed(seed)
    labelled = torch.stack(list(ds.hf_dataset["observation.action_labelled"])).reshape(-1) > 0.5
    pick = [torch.nonzero(labelled == flag).flatten() for flag in (True, False)]
    idx = [
        int(p[i])
        for p, n in zip(pick, (size - size // 2, size // 2), strict=True)
        for i in torch.randperm(len(p), generator=g)[:n]
    ]
    batch = torch.utils.data.default_collate([ds[i] for i in idx])
    marker = batch["observation.action_labelled"]
    assert (marker == 0).any() and (marker == 1).any()
    return batch


@pytest.fixture(scope="module")
def policy_and_batch(tiny_build):
    policy, pre, post = build_policy(tiny_build)
    torch.manual_seed(0)
    return policy, pre, post, pre(mixed_batch(policy.config))


def test_make_policy_from_dataset_metadata(policy_and_batch):
    policy, _, _, batch = policy_and_batch
    cfg = policy.config
    assert isinstance(policy, JEPTPolicy)
    assert cfg.image_key == "observation.image" and cfg.resolved_action_dim == 4
    assert cfg.input_features["observation.state"].shape == (18,)
    k = cfg.n_obs_steps
    assert batch["observation.image"].shape == (8, k + 1, 3, 64, 64)
    assert batch[PROMPT_VIDEO].shape[:3] == (8, 4, 3)
    assert batch["action"].dtype == torch.long and batch["action"].shape == (8, k, 4)


def test_forward_returns_both_losses_and_labelled_fraction(policy_and_batch):
    policy, _, _, batch = policy_and_batch
    policy.eval()
    loss, info = policy.forward(batch)
    assert loss.ndim == 0 and torch.isfinite(loss)
    assert {"loss_obs", "loss_act", "labelled_fraction"} <= set(info)
    labels = batch["action"].clone()
    labels[batch["action_is_pad"]] = IGNORE_INDEX
    expected = (labels != IGNORE_INDEX).all(-1).float().mean().item()
    assert 0 < expected < 1 and info["labelled_fraction"] == pytest.approx(expected)
    # the default recipe (plus): both prompt terms at weight 1 and the self-state change's loss, weight 1
    assert policy.config.recipe == "plus" and policy.config.idm_input == "self_state"
    extra = info["loss_prompt_align"] + info["loss_prompt_swap"] + info["loss_state"]
    assert loss.item() == pytest.approx(info["loss_obs"] + 8 * info["loss_act"] + extra, rel=1e-4)
    per_sample, _ = policy.forward(batch, reduction="none")
    assert per_sample.shape == (8,)


def test_paper_recipe_is_the_papers_objective_and_options_override_a_recipe(
    tiny_build, policy_and_batch, tmp_path
):
    """recipe=paper is the paper's L_obs + c * L_act with Gamma_act on the predictor's h_t+1 states, and nothing
    else runs; an option given explicitly overrides its recipe's value, and the checkpoint records both."""
    *_, batch = policy_and_batch
    policy, _, _ = build_policy(tiny_build, recipe="paper")
    cfg = policy.config
    assert (cfg.idm_input, cfg.prompt_align_weight, cfg.prompt_swap_weight, cfg.prompt_guidance) == (
        "embedding",
        0.0,
        0.0,
        0.0,
    )
    policy.eval()
    loss, info = policy.forward(batch)
    assert not {"loss_prompt_align", "loss_prompt_swap", "loss_state"} & set(info)
    assert loss.item() == pytest.approx(info["loss_obs"] + 8 * info["loss_act"], rel=1e-4)

    mixed = tiny_config(recipe="paper", idm_input="self_state")
    assert mixed.idm_input == "self_state" and mixed.prompt_swap_weight == 0.0
    mixed._save_pretrained(tmp_path)
    saved = json.loads((tmp_path / "config.json").read_text())
    assert saved["recipe"] == "paper" and saved["idm_input"] == "self_state"
    assert JEPTConfig.from_pretrained(tmp_path).idm_input == "self_state"
    plus = tiny_config(prompt_warmup_steps=100)
    assert (plus.recipe, plus.idm_input, plus.prompt_align_weight, plus.prompt_guidance) == (
        "plus",
        "self_state",
        1.0,
        1.0,
    )
    assert tiny_config().prompt_guidance == 0.0  # no prompt warm-up, no dropout: nothing to guide against
    with pytest.raises(ValueError, match="--policy.recipe=paper"):
        tiny_config(recipe="mine")


def test_prompt_losses_train_only_the_second_phase(tiny_build, policy_and_batch):
    """The alignment reaches the prompt encoder and its projections, never the joint embedding encoder; the
    swap term needs a batch with two tasks, and its gap is L_obs under another task's prompt minus L_obs."""
    *_, batch = policy_and_batch
    policy, _, _ = build_policy(tiny_build, prompt_swap_weight=0.0)
    policy.train()
    _, info = policy.forward(batch)
    m = policy.model
    align = m.prompt_align(
        m.encode_prompt(batch[PROMPT_VIDEO], batch.get("observation.prompt_video_mask")),
        torch.randn(8, 4, 5, policy.config.joint_embedding_dim),
        batch["task_index"],
        0.1,
    )
    align.backward()
    assert all(p.grad is None for p in m.encoder.parameters())
    assert any(p.grad is not None and p.grad.abs().sum() > 0 for p in m.prompt_encoder.parameters())
    assert len(set(batch["task_index"].tolist())) > 1 and info["loss_prompt_align"] > 0


def test_unlabelled_and_padded_actions_contribute_nothing(policy_and_batch):
    policy, _, _, batch = policy_and_batch
    policy.eval()
    torch.manual_seed(1)
    base, _ = policy.forward(batch)
    labels = batch["action"]
    unlabelled = (labels == IGNORE_INDEX).any(-1) | batch["action_is_pad"]
    assert unlabelled.any() and (~unlabelled).any()
    changed = dict(batch)
    changed["action"] = labels.clone()
    # a padded frame gets a valid but different label; a NaN-marked frame gets labels in its other dims
    changed["action"][unlabelled] = (labels[unlabelled].clamp_min(0) + 3) % 7
    changed["action"][(labels == IGNORE_INDEX).any(-1)] = torch.tensor([1, IGNORE_INDEX, 2, 3])
    changed["action_is_pad"] = batch["action_is_pad"]
    torch.manual_seed(1)
    assert policy.forward(changed)[0].item() == pytest.approx(base.item(), abs=1e-6)
    labelled = (~unlabelled).nonzero()[0]
    changed["action"][labelled[0], labelled[1]] = (labels[labelled[0], labelled[1]] + 1) % 7
    assert policy.forward(changed)[0].item() != pytest.approx(base.item(), abs=1e-6)


def test_action_bins_step_maps_nan_to_ignore_and_counts_clipping():
    from lerobot.processor import TransitionKey

    step = JeptActionBinsStep(num_bins=7, low=-1, high=1)
    action = torch.tensor([[-1.0, 0.0, 1.0, 0.34], [float("nan")] * 4, [2.0, -3.0, 0.5, -0.5]])
    out = step({TransitionKey.ACTION: action})[TransitionKey.ACTION]
    assert out.tolist() == [[0, 3, 6, 4], [IGNORE_INDEX] * 4, [6, 0, 4, 2]]  # ties round half to even
    assert (step.num_clipped, step.num_values) == (2, 8)
    assert step({TransitionKey.ACTION: None})[TransitionKey.ACTION] is None  # inference: no action


def test_action_bins_step_reads_the_label_marker_and_drops_it():
    """observation.action_labelled over the observation window (k + 1 frames for jept) marks the action frames
    (the first k); the marker never reaches the model."""
    from lerobot.processor import TransitionKey

    step = JeptActionBinsStep(num_bins=7, low=-1, high=1)
    action = torch.zeros(2, 3, 4)  # (B, k, A): the neutral action everywhere
    marker = torch.tensor([[1.0, 0.0, 1.0, 0.0], [0.0, 0.0, 0.0, 1.0]])[..., None]  # (B, k + 1, 1)
    out = step(
        {TransitionKey.ACTION: action, TransitionKey.OBSERVATION: {"observation.action_labelled": marker}}
    )
    assert out[TransitionKey.OBSERVATION] == {}
    labels = out[TransitionKey.ACTION]
    assert (labels[:, :, 0] == IGNORE_INDEX).tolist() == [[False, True, False], [True, True, True]]
    assert (labels[labels != IGNORE_INDEX] == 3).all()
    idm = step(
        {
            TransitionKey.ACTION: torch.zeros(2, 4),
            TransitionKey.OBSERVATION: {"observation.action_labelled": marker[:, :2]},
        }
    )
    assert (idm[TransitionKey.ACTION][:, 0] == IGNORE_INDEX).tolist() == [
        False,
        True,
    ]  # (B, A), frames [0, 1]


def test_ema_update_moves_targets_and_only_targets(tiny_build):
    policy, pre, _ = build_policy(tiny_build, ema_decay=0.5)
    model = policy.model
    with torch.no_grad():
        for p in model.encoder.parameters():
            p.add_(0.1)
    online = copy.deepcopy(model.encoder.state_dict())
    target = copy.deepcopy(model.target_encoder.state_dict())
    policy.update()
    for name, value in model.target_encoder.state_dict().items():
        if value.is_floating_point():
            torch.testing.assert_close(value, 0.5 * target[name] + 0.5 * online[name])
    for name, value in model.encoder.state_dict().items():
        torch.testing.assert_close(value, online[name])
    assert not any(p.requires_grad for p in model.target_encoder.parameters())
    assert int(policy.num_updates) == 1


def test_alternating_phases_update_only_their_parameters(tiny_build):
    policy, pre, _ = build_policy(tiny_build, phase_schedule="alternate", phase_steps=1)
    batch = pre(mixed_batch(policy.config, size=4))
    optimizer = torch.optim.AdamW(policy.get_optim_params(), weight_decay=1e-2)
    modules = policy.model.phase_modules()
    modules["encoder"].append(policy.model.backbone)  # the small config trains its backbone in this phase
    policy.train()
    for expected in ("encoder", "others", "encoder"):
        assert policy.phase == expected
        before = {
            n: [p.detach().clone() for p in m.parameters()] for n, ms in modules.items() for m in ms[:1]
        }
        loss, info = policy.forward(batch)
        loss.backward()
        optimizer.step()
        optimizer.zero_grad()
        policy.update()
        for name, params in before.items():
            first = modules[name][0]
            moved = any(not torch.equal(a, b) for a, b in zip(params, first.parameters(), strict=True))
            assert moved == (name == expected), (expected, name)
        assert info["phase_encoder"] == float(expected == "encoder")


def test_prompt_warmup_excludes_the_prompt_at_first(tiny_build):
    policy, pre, _ = build_policy(tiny_build, prompt_warmup_steps=2)
    batch = pre(mixed_batch(policy.config, size=2))
    assert policy.forward(batch)[1]["prompt_on"] == 0.0
    policy.update()
    policy.update()
    assert policy.forward(batch)[1]["prompt_on"] == 1.0


def test_save_and_reload_gives_identical_outputs_and_processors(policy_and_batch, tmp_path):
    policy, pre, post, batch = policy_and_batch
    policy.eval()
    policy.save_pretrained(tmp_path)
    pre.save_pretrained(tmp_path)
    post.save_pretrained(tmp_path)
    saved = set(load_file(tmp_path / "model.safetensors"))
    assert saved == set(policy.state_dict())  # strict=False loading would hide a missing key
    reloaded = JEPTPolicy.from_pretrained(tmp_path).eval()
    pre2 = PolicyProcessorPipeline.from_pretrained(tmp_path, "policy_preprocessor.json")
    assert [type(s).__name__ for s in pre2.steps] == [type(s).__name__ for s in pre.steps]
    assert pre2.steps[2].get_config() == pre.steps[2].get_config()
    torch.manual_seed(0)
    a = policy.forward(batch)[0]
    torch.manual_seed(0)
    b = reloaded.forward(batch)[0]
    torch.testing.assert_close(a, b)
    obs = {
        "observation.image": batch["observation.image"][:2, -1],
        "observation.state": batch["observation.state"][:2, -1],
    }
    obs[PROMPT_VIDEO] = batch[PROMPT_VIDEO][:2]
    policy.reset()
    reloaded.reset()
    torch.testing.assert_close(policy.select_action(obs), reloaded.select_action(obs))


@pytest.mark.parametrize(
    "overrides",
    [{}, {"recipe": "paper"}, {"prompt_dropout": 0.2, "prompt_guidance": 1.0}, {"bc_head_weight": 8.0}],
    ids=["plus", "paper", "guided", "bc_head"],
)
def test_cached_and_uncached_control_give_the_same_actions(tiny_build, overrides):
    """The cached control (frame tokens, the prompt's layer inputs, the last layer on o_t alone) gives the logits
    of full recomputation, for either inverse dynamics and with guidance's second prediction."""
    policy, pre, post = build_policy(tiny_build, **overrides)
    uncached = copy.deepcopy(policy)
    uncached.config = copy.deepcopy(policy.config)
    uncached.config.cache_frame_tokens = False
    policy.eval(), uncached.eval()
    logits = {}
    for name, p in (("cached", policy), ("uncached", uncached)):
        control = p._control_logits
        p._control_logits = lambda *a, name=name, control=control: (
            logits.setdefault(name, []).append(control(*a)) or logits[name][-1]
        )
    ds = load(MIX)
    episode = ds.meta.episodes[0]
    frames = [ds[episode["dataset_from_index"] + i] for i in range(7)]  # wraps the k = 4 context
    for p in (policy, uncached):
        p.reset()
    for frame in frames:
        obs = pre(
            {
                "observation.image": frame["observation.image"],
                "observation.state": frame["observation.state"],
                "task": frame["task"],
            }
        )
        a, b = policy.select_action(obs), uncached.select_action(obs)
        assert a.shape == (1, 4)
        torch.testing.assert_close(a, b)
        torch.testing.assert_close(logits["cached"][-1], logits["uncached"][-1], atol=1e-5, rtol=1e-4)
        centres = torch.linspace(-1, 1, 7)
        assert (post(a)[..., None] - centres).abs().min(-1).values.max() < 1e-6  # executed: bin centres


def overfit(policy, pre, steps: int = 40) -> tuple[dict, dict]:
    """AdamW steps on one small mixed batch -> the loss info of the first forward and of the last."""
    batch = pre(mixed_batch(policy.config, size=4, seed=3))
    optimizer = torch.optim.AdamW(policy.parameters(), lr=1e-3)
    policy.train()
    first = policy.forward(batch)[1]
    for _ in range(steps):
        loss, info = policy.forward(batch)
        optimizer.zero_grad()
        loss.backward()
        optimizer.step()
        policy.update()
    return first, info


def test_overfits_a_tiny_batch(tiny_build):
    policy, pre, _ = build_policy(tiny_build)
    first, info = overfit(policy, pre)
    assert info["loss_act"] < 0.5 * first["loss_act"]
    assert info["loss_obs"] < first["loss_obs"]


def test_prompt_bank_lookup(tiny_build):
    from lerobot.processor import TransitionKey

    policy, pre, _ = build_policy(tiny_build)
    step = pre.steps[2]
    control = {
        TransitionKey.OBSERVATION: {},
        TransitionKey.COMPLEMENTARY_DATA: {"task": ["Press a handle down"]},
    }
    assert step(control) is control  # control: the policy's own config names the prompt
    image = {"observation.image": torch.zeros(1, 3, 64, 64), "task": ["Press a handle down"]}
    first = policy.deployment_prompt(image)[PROMPT_VIDEO]
    torch.testing.assert_close(
        first, policy.deployment_prompt(image)[PROMPT_VIDEO]
    )  # the task's first prompt
    assert first.shape == (1, 4, 3, 64, 64) and first.dtype == torch.uint8  # bank prompts travel as uint8
    assert (first.float() / 255).std() > 0.05
    training = {
        **control,
        TransitionKey.COMPLEMENTARY_DATA: {"task": ["Press a handle down"] * 16, "index": torch.arange(16)},
    }
    videos = step(training)[TransitionKey.OBSERVATION][PROMPT_VIDEO]
    assert any(not torch.equal(videos[0], v) for v in videos[1:])  # training: random prompt of the task
    given = torch.rand(1, 3, 3, 32, 32)
    out = step({**control, TransitionKey.OBSERVATION: {PROMPT_VIDEO: given}})[TransitionKey.OBSERVATION]
    assert out[PROMPT_VIDEO].shape == (1, 3, 3, 64, 64)  # the caller's prompt, at model resolution
    as_uint8 = step({**control, TransitionKey.OBSERVATION: {PROMPT_VIDEO: first}})[TransitionKey.OBSERVATION]
    torch.testing.assert_close(as_uint8[PROMPT_VIDEO], first.float() / 255)  # a uint8 prompt means 0-255
    with pytest.raises(PromptNotFoundError, match=r"'Open a door'.*test/mw_tiny_prompts"):
        step(
            {
                **training,
                TransitionKey.COMPLEMENTARY_DATA: {"task": ["Open a door"], "index": torch.arange(1)},
            }
        )
    with pytest.raises(PromptNotFoundError, match=r"'Open a door'"):
        policy.deployment_prompt({**image, "task": ["Open a door"]})


def test_prompt_video_file_is_the_prompt_in_control(tiny_build, tmp_path):
    from lerobot_jept.policies.prompts import PromptBank, load_prompt_video, subsample_indices

    policy, pre, _ = build_policy(tiny_build)
    bank = PromptBank(PROMPTS, None, 1000, 64)
    frames = bank.video(bank.episodes("Press a handle down")[1])  # not the bank's first prompt of the task
    clip = tmp_path / "clip.mp4"
    write_clip(frames, clip)
    decoded = load_prompt_video(clip, 4, 64)
    expected = frames[subsample_indices(len(frames), 4)]
    assert decoded.shape == (4, 3, 64, 64) and decoded.dtype == torch.uint8
    assert (decoded.float() - expected.float()).abs().mean() < 8  # the same frames, through a lossy codec

    ds = load(MIX)
    frame = ds[0]
    obs = pre(
        {"observation.image": frame["observation.image"], "observation.state": frame["observation.state"]}
    )
    policy.eval()
    policy.config.prompt_video = str(clip)
    policy.reset()
    from_file = policy.select_action(obs)
    policy.reset()
    given = policy.select_action({**obs, PROMPT_VIDEO: decoded[None].float() / 255})
    torch.testing.assert_close(from_file, given)
    policy.config.prompt_video = str(tmp_path / "missing.mp4")
    policy.reset()
    with pytest.raises(FileNotFoundError, match="--policy.prompt_video"):
        policy.select_action(obs)


def test_checkpoints_carry_no_local_path(tiny_build, tmp_path):
    import json

    policy, pre, _ = build_policy(
        tiny_build, prompt_root="/somewhere/local", prompt_video="/home/me/clip.mp4"
    )
    policy.save_pretrained(tmp_path)
    pre.save_pretrained(tmp_path)
    saved = (tmp_path / "config.json").read_text() + (tmp_path / "policy_preprocessor.json").read_text()
    assert "/somewhere/local" not in saved and "clip.mp4" not in saved
    assert json.loads((tmp_path / "config.json").read_text())["prompt_repo_id"] == PROMPTS
    assert policy.config.prompt_root == "/somewhere/local"  # the live config keeps its paths
    reloaded = JEPTPolicy.from_pretrained(
        tmp_path, prompt_video="/data/clip.mp4", prompt_repo_id="other/bank"
    )
    assert reloaded.config.prompt_video == "/data/clip.mp4" and reloaded.config.prompt_repo_id == "other/bank"


@pytest.mark.parametrize(
    "change, message",
    [
        (lambda f: f.pop("observation.image"), "needs a camera image"),
        (lambda f: f.pop("observation.state"), "self-state"),
    ],
)
def test_validate_features_names_the_fix(change, message):
    features = {
        "observation.image": PolicyFeature(FeatureType.VISUAL, (3, 64, 64)),
        "observation.state": PolicyFeature(FeatureType.STATE, (18,)),
    }
    change(features)
    cfg = tiny_config(
        input_features=features, output_features={"action": PolicyFeature(FeatureType.ACTION, (4,))}
    )
    with pytest.raises(ValueError, match=message):
        cfg.validate_features()


def test_validate_features_action_checks():
    inputs = {
        "observation.image": PolicyFeature(FeatureType.VISUAL, (3, 64, 64)),
        "observation.state": PolicyFeature(FeatureType.STATE, (18,)),
    }
    with pytest.raises(ValueError, match="flatten"):
        tiny_config(
            input_features=inputs, output_features={"action": PolicyFeature(FeatureType.ACTION, (2, 4))}
        ).validate_features()
    with pytest.raises(ValueError, match="drop --policy.action_dim"):
        tiny_config(
            input_features=inputs,
            action_dim=7,
            output_features={"action": PolicyFeature(FeatureType.ACTION, (4,))},
        ).validate_features()
    with pytest.raises(ValueError, match="--policy.action_dim=N"):
        tiny_config(input_features=inputs, output_features={}).validate_features()
    tiny_config(
        input_features=inputs, output_features={}, action_dim=4
    ).validate_features()  # expert videos only


@pytest.mark.parametrize("history", [0, 1])
def test_self_state_inverse_dynamics_trains_and_controls_from_the_predicted_change(
    tiny_build, tmp_path, history
):
    """idm_input=self_state: Gamma_state learns the self-state change on every frame, the inverse dynamics learns
    the actions from the real change (with idm_history, and the observed change into s_t), and control acts on the
    predicted change: select_action over an episode's frames gives what offline_outputs' control gives on the
    same window; the running scale is saved."""
    from lerobot.datasets.lerobot_dataset import LeRobotDatasetMetadata

    policy, pre, _ = build_policy(tiny_build, idm_input="self_state", idm_history=history)
    assert policy.model.action_head is None and policy.model.state_dynamics is not None
    state_dim = policy.config.input_features["observation.state"].shape[0]
    assert policy.model.state_dynamics.inverse.mlp[0].in_features == (2 + history) * state_dim
    first, info = overfit(policy, pre)
    assert {"loss_state", "loss_act", "loss_obs"} <= set(first)
    assert info["loss_act"] < 0.5 * first["loss_act"]
    assert info["loss_state"] < 0.5 * first["loss_state"]
    scale = policy.model.state_dynamics.scale
    assert int(policy.model.state_dynamics.scale_updates) == 41 and not torch.allclose(
        scale, torch.ones_like(scale)
    )

    policy.eval()
    k = policy.config.n_obs_steps
    ds = load(MIX, delta_timestamps=resolve_delta_timestamps(policy.config, LeRobotDatasetMetadata(MIX)))
    start = ds.meta.episodes[0]["dataset_from_index"]
    window = pre(torch.utils.data.default_collate([ds[start + k - 1]]))  # frames 0..k: context 0..k-1
    offline = policy.offline_outputs(window)["control"].argmax(-1)
    policy.reset()
    for i in range(k):
        obs = {key: window[key][:, i] for key in ("observation.image", "observation.state")}
        action = policy.select_action({**obs, PROMPT_VIDEO: window[PROMPT_VIDEO]})
    torch.testing.assert_close(action, policy.bin_centres[offline])

    policy.save_pretrained(tmp_path)
    reloaded = JEPTPolicy.from_pretrained(tmp_path).eval()
    torch.testing.assert_close(reloaded.model.state_dynamics.scale, scale)
    torch.testing.assert_close(
        reloaded.offline_outputs(window)["control"], policy.offline_outputs(window)["control"]
    )


def test_change_consistency_trains_the_change_predictor_not_the_inverse_dynamics(tiny_build):
    """change_consistency_weight: the cross-entropy of the actions read from the predicted change against the
    inverse dynamics' bin probabilities from the real one, over real frames past the history; its gradient
    reaches the predicted change and never the inverse dynamics; it is the entropy of those probabilities (its
    least) when the predicted change is the real one; it falls when training."""
    policy, pre, _ = build_policy(
        tiny_build, idm_input="self_state", idm_history=1, change_consistency_weight=1.0
    )
    sd, k = policy.model.state_dynamics, policy.config.n_obs_steps
    sd.scale.fill_(0.05)
    state = pre(mixed_batch(policy.config, size=4, seed=3))["observation.state"]  # (B, k + 1, S)
    real_change = sd.change_of(state)
    real = sd(state[:, :k], real_change, sd.past_changes(state[:, :k]))
    ok = torch.ones(state.shape[0], k)
    ok[0, -1] = 0.0  # a padded next frame
    predicted = torch.randn_like(real_change, requires_grad=True)
    term = policy._change_consistency(state, predicted, real, ok)

    by_hand = torch.zeros(state.shape[0])
    for b in range(state.shape[0]):
        frames = [t for t in range(1, k) if ok[b, t]]  # history 1: not the first frame
        for t in frames:
            logits = sd(state[b, t], predicted[b, t], real_change[b, t - 1])
            by_hand[b] += -(real[b, t].softmax(-1) * logits.log_softmax(-1)).sum(-1).mean() / len(frames)
    torch.testing.assert_close(term, by_hand)

    term.sum().backward()
    assert predicted.grad.abs().sum() > 0
    assert all(p.grad is None for p in sd.parameters())
    at_real = policy._change_consistency(state, real_change, real, ok)
    entropy = -(real.softmax(-1) * real.log_softmax(-1)).sum(-1).mean(-1)
    torch.testing.assert_close(at_real, frame_mean(entropy[:, 1:], ok[:, 1:]))
    assert (at_real < term).all()

    first, info = overfit(policy, pre)
    assert info["loss_consistency"] < first["loss_consistency"]
    off = build_policy(tiny_build, idm_input="self_state")[0]
    assert "loss_consistency" not in off.forward(pre(mixed_batch(policy.config, size=2)))[1]
    with pytest.raises(ValueError, match="change_consistency_weight must be in"):
        tiny_config(idm_input="self_state", change_consistency_weight=-1.0)
    with pytest.raises(ValueError, match="add --policy.idm_input=self_state"):
        tiny_config(idm_input="embedding", change_consistency_weight=1.0)


@pytest.mark.parametrize("recipe", ["plus", "paper"])
def test_bc_head_learns_demo_and_relabelled_video_actions_and_is_what_control_reads(tiny_build, recipe):
    """bc_head_weight: the BC head's cross-entropy is against the demo's action on a labelled frame and against
    the inverse dynamics' most likely bins from the real next frame on a video frame (none on a padded next
    frame, none on the history's frames), its gradient never reaches the inverse dynamics' logits, it falls
    when training, and control (online and offline) executes the BC head's bins, not the inverse dynamics'."""
    history = 1 if recipe == "plus" else 0
    policy, pre, _ = build_policy(tiny_build, recipe=recipe, idm_history=history, bc_head_weight=1.0)
    k, bins = policy.config.n_obs_steps, policy.config.num_action_bins
    batch = pre(mixed_batch(policy.config, size=4, seed=3))
    labels = policy.action_labels(batch, torch.Size([4, k, 4]))
    assert (labels == IGNORE_INDEX).any() and (labels != IGNORE_INDEX).any()
    bc = torch.randn(4, k, 4, bins, requires_grad=True)
    inverse = torch.randn(4, k, 4, bins, requires_grad=True)
    ok = torch.ones(4, k)
    ok[:, -1] = 0.0  # padded next frames
    term = policy._bc_loss(batch, bc, inverse, ok)

    by_hand = torch.zeros(4)
    for b in range(4):
        targets = {}
        for t in range(history, k):
            if labels[b, t, 0] != IGNORE_INDEX:
                targets[t] = labels[b, t]
            elif ok[b, t]:
                targets[t] = inverse[b, t].argmax(-1)
        for t, target in targets.items():
            by_hand[b] += torch.nn.functional.cross_entropy(bc[b, t], target) / len(targets)
    torch.testing.assert_close(term, by_hand)
    term.sum().backward()
    assert bc.grad.abs().sum() > 0 and inverse.grad is None

    first, info = overfit(policy, pre)
    assert info["loss_bc"] < 0.5 * first["loss_bc"]
    policy.eval()
    out = policy.model.bc_head.out[-1]  # every dimension's logits favour bin 5, whatever the input
    with torch.no_grad():
        out.weight.zero_()
        out.bias.copy_(torch.nn.functional.one_hot(torch.tensor(5), bins).float())
    policy.reset()
    obs = {key: batch[key][:, k - 1] for key in ("observation.image", "observation.state")}
    action = policy.select_action({**obs, PROMPT_VIDEO: batch[PROMPT_VIDEO]})
    torch.testing.assert_close(action, policy.bin_actions(torch.full((4, 4), 5)))
    assert (policy.offline_outputs(batch)["control"].argmax(-1) == 5).all()
    assert not (policy.offline_outputs(batch)["inverse"].argmax(-1) == 5).all()

    off = build_policy(tiny_build, recipe=recipe)[0]
    assert off.model.bc_head is None and "loss_bc" not in off.forward(batch)[1]
    with pytest.raises(ValueError, match="bc_head_weight must be in"):
        tiny_config(bc_head_weight=-1.0)
    with pytest.raises(ValueError, match="drop --policy.chunk_size"):
        tiny_config(bc_head_weight=1.0, chunk_size=2)


def test_idm_input_must_be_known():
    with pytest.raises(ValueError, match="--policy.idm_input=embedding"):
        tiny_config(idm_input="state")
    with pytest.raises(ValueError, match="idm_history must be in"):
        tiny_config(idm_input="self_state", idm_history=tiny_config().n_obs_steps)
    with pytest.raises(ValueError, match="add --policy.idm_input=self_state"):
        tiny_config(idm_input="embedding", idm_history=1)


def test_past_changes_are_the_scaled_changes_into_each_frame_oldest_first():
    from lerobot_jept.policies.components.predictor import SelfStateInverseDynamics

    sd = SelfStateInverseDynamics(8, 2, 4, 7, 16, 2, history=2)
    sd.scale.fill_(2.0)
    state = torch.tensor([[[0.0, 0.0], [1.0, 2.0], [3.0, 6.0], [6.0, 12.0]]])  # changes (1,2) (2,4) (3,6)
    past = sd.past_changes(state)
    assert past.shape == (1, 4, 4)
    expected = torch.tensor([[0, 0, 0, 0], [0, 0, 1, 2], [1, 2, 2, 4], [2, 4, 3, 6]]).float() / 2
    torch.testing.assert_close(past[0], expected)
    logits = sd(state[:, :3], sd.change_of(state), past[:, :3])
    assert logits.shape == (1, 3, 4, 7)
    with pytest.raises(ValueError, match="pass `past`"):
        sd(state[:, :3], sd.change_of(state))
    assert SelfStateInverseDynamics(8, 2, 4, 7, 16, 2).past_changes(state).shape == (1, 4, 0)


def test_chunk_targets_and_chunk_logits_by_hand():
    """Frame j's i-th target is the scaled change from frame j + i into j + i + 1, masked where the window ends or
    the next frame is padding; the i-th action of a chunk is read from the state its i predicted changes reach,
    with the change into that state (observed, then predicted) as its past."""
    from lerobot_jept.policies.components.predictor import SelfStateInverseDynamics

    sd = SelfStateInverseDynamics(8, 2, 4, 7, 16, 2, history=1, chunk=3)
    sd.scale.fill_(2.0)
    state = torch.tensor([[[0.0, 0.0], [1.0, 2.0], [3.0, 6.0], [6.0, 12.0]]])  # changes (1,2) (2,4) (3,6)
    frame_ok = torch.tensor([[1.0, 1.0, 0.0]])  # the last frame is padding
    target, ok = sd.chunk_targets(state, frame_ok)
    assert target.shape == (1, 3, 3, 2) and ok.shape == (1, 3, 3)
    changes = torch.tensor([[1.0, 2.0], [2.0, 4.0], [3.0, 6.0]]) / 2
    torch.testing.assert_close(target[0, 0], changes)
    torch.testing.assert_close(target[0, 1, :2], changes[1:])
    torch.testing.assert_close(ok[0], torch.tensor([[1.0, 1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 0.0]]))

    observed = state[:, :2]  # s_{t-1}, s_t
    predicted = torch.tensor(
        [[[0.5, 0.5], [1.0, -1.0], [0.0, 2.0]]]
    )  # scaled: (1, 1), (2, -2), (0, 4) in units
    logits = sd.chunk_logits(observed, predicted)
    assert logits.shape == (1, 3, 4, 7)
    s_t = observed[:, -1]
    reached = [s_t, s_t + torch.tensor([1.0, 1.0]), s_t + torch.tensor([3.0, -1.0])]
    past = [sd.change_of(observed)[:, -1], predicted[:, 0], predicted[:, 1]]
    for i in range(3):
        torch.testing.assert_close(logits[:, i], sd(reached[i], predicted[:, i], past[i]))
    one = SelfStateInverseDynamics(8, 2, 4, 7, 16, 2)
    torch.testing.assert_close(one.chunk_logits(observed, predicted[:, :1])[:, 0], one(s_t, predicted[:, 0]))


def test_action_chunks_train_and_execute_n_action_steps_per_prediction(tiny_build, tmp_path):
    """chunk_size=3: Gamma_state predicts three changes per frame and learns them; control predicts once every
    n_action_steps steps and executes the chunk's actions in order (what offline control decodes for the
    first); the chunk's loss at chunk_size=1 is the one-change loss."""
    from lerobot.datasets.lerobot_dataset import LeRobotDatasetMetadata

    policy, pre, _ = build_policy(tiny_build, chunk_size=3, n_action_steps=3)
    state_dim = policy.config.input_features["observation.state"].shape[0]
    assert policy.model.state_dynamics.change_head.mlp[-1].out_features == 3 * state_dim
    first, info = overfit(policy, pre)
    assert info["loss_state"] < 0.5 * first["loss_state"]

    policy.eval()
    k = policy.config.n_obs_steps
    ds = load(MIX, delta_timestamps=resolve_delta_timestamps(policy.config, LeRobotDatasetMetadata(MIX)))
    start = ds.meta.episodes[0]["dataset_from_index"]
    window = pre(torch.utils.data.default_collate([ds[start + k - 1]]))
    predictions = []
    control = policy._control_logits
    policy._control_logits = lambda *a: predictions.append(control(*a)) or predictions[-1]
    for n_action_steps in (3, 1):
        policy.config.n_action_steps = n_action_steps
        predictions.clear()
        policy.reset()
        actions = []
        for i in range(k):
            obs = {key: window[key][:, i] for key in ("observation.image", "observation.state")}
            actions.append(policy.select_action({**obs, PROMPT_VIDEO: window[PROMPT_VIDEO]}))
        assert len(predictions) == -(-k // n_action_steps)
        assert predictions[0].shape == (1, 3, 4, 7)
        executed = torch.cat([policy.bin_centres[p[:, :n_action_steps].argmax(-1)] for p in predictions], 1)
        torch.testing.assert_close(torch.stack(actions, 1), executed.view(1, -1, 4)[:, :k])
    torch.testing.assert_close(
        policy.offline_outputs(window)["control"].argmax(-1), predictions[-1][:, 0].argmax(-1)
    )

    one, _, _ = build_policy(tiny_build)
    batch = pre(mixed_batch(one.config, size=4, seed=3))
    _, obs, h_in = one._encode_window(batch)
    change = one.model.predict(None, obs[:, :k], h_in, batch["observation.state"])[2]
    target, ok = one.model.state_dynamics.chunk_targets(batch["observation.state"], torch.ones(4, k))
    torch.testing.assert_close(
        target[:, :, 0], one.model.state_dynamics.change_of(batch["observation.state"])
    )
    assert change.shape == (4, k, 1, state_dim) and bool(ok.all())


def test_action_chunks_are_checked():
    with pytest.raises(ValueError, match="chunk_size must be in"):
        tiny_config(chunk_size=tiny_config().n_obs_steps + 1)
    with pytest.raises(ValueError, match="add --policy.idm_input=self_state"):
        tiny_config(recipe="paper", chunk_size=2)
    with pytest.raises(ValueError, match="n_action_steps must be in"):
        tiny_config(chunk_size=2, n_action_steps=3)


@pytest.mark.parametrize("idm_input, dropout", [("embedding", 0.5), ("self_state", 0.5), ("self_state", 0.0)])
def test_prompt_guidance_moves_the_prediction_away_from_the_null_prompt(
    tiny_build, tmp_path, idm_input, dropout
):
    """prompt_dropout trains a null prompt (in the prompt learning-rate group, saved with the checkpoint);
    prompt_guidance w turns the control prediction x (the action logits, or the self-state change) into
    x + w (x - x_null), the same in offline_outputs and select_action, and 0 leaves it as it was. Without
    dropout x_null is the prediction without a prompt (the prompt warm-up's)."""
    from lerobot.datasets.lerobot_dataset import LeRobotDatasetMetadata

    policy, pre, _ = build_policy(
        tiny_build, idm_input=idm_input, prompt_dropout=dropout, prompt_warmup_steps=1, prompt_guidance=0.0
    )
    m = policy.model
    policy.train()
    policy.update()  # past the warm-up
    torch.manual_seed(1)
    policy.forward(pre(mixed_batch(policy.config)))[0].backward()
    if dropout:
        assert any(p is m.null_prompt.tokens for p in policy.get_optim_params()[1]["params"])
        assert m.null_prompt.tokens.grad.abs().sum() > 0
    else:
        assert m.null_prompt is None

    policy.eval()
    k = policy.config.n_obs_steps
    ds = load(MIX, delta_timestamps=resolve_delta_timestamps(policy.config, LeRobotDatasetMetadata(MIX)))
    window = pre(torch.utils.data.default_collate([ds[i] for i in (k - 1, k + 5)]))
    plain = policy.offline_outputs(window)["control"]

    prompt = m.encode_prompt(window[PROMPT_VIDEO], window.get("observation.prompt_video_mask"))
    null_prompt = m.null_prompt(prompt) if dropout else None
    _, obs, h_in = policy._encode_window(window)
    if idm_input == "self_state":
        change, null_change = (m.predict(p, obs[:, :k], h_in)[2][:, -1, 0] for p in (prompt, null_prompt))
        expected = m.state_dynamics(
            window["observation.state"][:, k - 1], change + 2 * (change - null_change)
        )
    else:
        null = policy._control_logits(null_prompt, obs[:, :k], h_in[:, : k - 1], None)[:, 0]
        expected = plain + 2 * (plain - null)
    policy.config.prompt_guidance = 2.0
    guided = policy.offline_outputs(window)["control"]
    torch.testing.assert_close(guided, expected)
    assert not torch.allclose(guided, plain)

    policy.reset()
    for i in range(k):
        obs_i = {key: window[key][:1, i] for key in ("observation.image", "observation.state")}
        action = policy.select_action({**obs_i, PROMPT_VIDEO: window[PROMPT_VIDEO][:1]})
    torch.testing.assert_close(action, policy.bin_centres[guided[:1].argmax(-1)])

    policy.save_pretrained(tmp_path)
    reloaded = JEPTPolicy.from_pretrained(tmp_path).eval()
    torch.testing.assert_close(reloaded.offline_outputs(window)["control"], guided)


def test_prompt_guidance_needs_a_null_prompt(tiny_build):
    from lerobot_jept.evaluation.cli_args import PolicyArg

    assert build_policy(tiny_build)[0].model.null_prompt is None  # the paper's checkpoints: no new weights
    with pytest.raises(ValueError, match="--policy.prompt_dropout=P"):
        tiny_config(prompt_guidance=2.0)
    with pytest.raises(ValueError, match="prompt_dropout is a probability"):
        tiny_config(prompt_dropout=1.0)
    with pytest.raises(ValueError, match="--policy.prompt_dropout=P"):
        PolicyArg("ckpt", prompt_guidance=2.0).apply(tiny_config())
    cfg = tiny_config(prompt_dropout=0.2)
    PolicyArg("ckpt", prompt_guidance=2.0).apply(cfg)
    assert cfg.prompt_guidance == 2.0


def test_optimizer_flags_are_refused_not_ignored(monkeypatch):
    """LeRobot replaces --optimizer.* with the policy's preset: the preset refuses them, naming the fix."""
    monkeypatch.setattr(sys, "argv", ["lerobot-train", "--policy.type=jept", "--optimizer.lr=1e-3"])
    with pytest.raises(ValueError, match=r"--optimizer.lr would be ignored.*--policy.optimizer_lr_encoder"):
        JEPTConfig().get_optimizer_preset()
    monkeypatch.setattr(
        sys, "argv", ["lerobot-train", "--policy.type=jept", "--policy.optimizer_lr_encoder=1e-3"]
    )
    preset = JEPTConfig(optimizer_lr_predictor=2e-4).get_optimizer_preset()
    assert preset.lr == 2e-4


def test_logged_learning_rates_name_their_groups_and_follow_the_optimizer(tiny_build):
    """``lr_<group>`` in the training log equals the rate LeRobot's optimizer and scheduler (the presets) apply
    to that group at that step, warm-up included."""
    policy, pre, _ = build_policy(tiny_build, scheduler_warmup_steps=3)
    cfg = policy.config
    optimizer = cfg.get_optimizer_preset().build(policy.get_optim_params())
    scheduler = cfg.get_scheduler_preset().build(optimizer, 100)
    assert [g["name"] for g in optimizer.param_groups] == ["encoder", "prompt", "predictor"]
    batch = pre(mixed_batch(cfg, size=2))
    policy.train()
    for _ in range(5):
        loss, info = policy.forward(batch)
        for group in optimizer.param_groups:
            assert info[f"lr_{group['name']}"] == pytest.approx(group["lr"])
        loss.backward()
        optimizer.step()
        optimizer.zero_grad()
        scheduler.step()
        policy.update()
    assert info["lr_encoder"] == pytest.approx(cfg.optimizer_lr_encoder)  # past the warm-up


def test_action_decoding_and_smoothing_in_control(tiny_build):
    """action_decoding=expectation executes the mean of the bin centres under the softmax of the logits that
    offline_outputs' control gives (between neighbouring centres, not only on them); action_smoothing b mixes
    each action with the episode's previous one, and reset() forgets it. Unknown or out-of-range values are
    refused with the flag to pass."""
    from lerobot.datasets.lerobot_dataset import LeRobotDatasetMetadata

    policy, pre, _ = build_policy(tiny_build, idm_input="self_state", action_decoding="expectation")
    overfit(policy, pre, steps=10)
    policy.eval()
    k = policy.config.n_obs_steps
    ds = load(MIX, delta_timestamps=resolve_delta_timestamps(policy.config, LeRobotDatasetMetadata(MIX)))
    start = ds.meta.episodes[0]["dataset_from_index"]
    windows = [pre(torch.utils.data.default_collate([ds[start + k - 1 + i]])) for i in range(2)]
    expected = [
        (policy.offline_outputs(w)["control"].softmax(-1) * policy.bin_centres).sum(-1) for w in windows
    ]

    def episode(b: float) -> list[torch.Tensor]:
        policy.config.action_smoothing = b
        policy.reset()
        actions = []
        for i in range(
            k + 1
        ):  # the context of the first window, then the next frame (the second window's last)
            w, j = (windows[0], i) if i < k else (windows[1], k - 1)
            obs = {key: w[key][:, j] for key in ("observation.image", "observation.state")}
            actions.append(policy.select_action({**obs, PROMPT_VIDEO: w[PROMPT_VIDEO]}))
        return actions[-2:]

    plain = episode(0.0)
    for got, want in zip(plain, expected, strict=True):
        torch.testing.assert_close(got, want, atol=1e-4, rtol=1e-4)  # cached and full passes round apart
    centres = policy.bin_centres
    assert ((plain[0][..., None] - centres).abs().min(-1).values > 1e-4).any()  # not only bin centres
    smoothed = episode(0.5)
    torch.testing.assert_close(smoothed[1], 0.5 * plain[1] + 0.5 * smoothed[0])
    assert not torch.allclose(smoothed[1], plain[1])

    with pytest.raises(ValueError, match="--policy.action_decoding=argmax"):
        tiny_config(action_decoding="mean")
    with pytest.raises(ValueError, match=r"action_smoothing must be in \[0, 1\)"):
        tiny_config(action_smoothing=1.0)

    # the evaluation tools' --policy.action_decoding / --policy.action_smoothing, onto any policy type's checkpoint
    from lerobot_jept.evaluation.cli_args import PolicyArg
    from lerobot_jept.policies.dt_star.configuration_dt_star import DTStarConfig

    cfg = tiny_config(DTStarConfig)
    PolicyArg("ckpt", action_decoding="expectation", action_smoothing=0.3).apply(cfg)
    assert (cfg.action_decoding, cfg.action_smoothing) == ("expectation", 0.3)
    with pytest.raises(ValueError, match="--policy.action_decoding=argmax"):
        PolicyArg("ckpt", action_decoding="mode").apply(cfg)
    with pytest.raises(ValueError, match="--policy.prompt_guidance is a jept option"):
        PolicyArg("ckpt", prompt_guidance=1.0).apply(tiny_config(DTStarConfig))
