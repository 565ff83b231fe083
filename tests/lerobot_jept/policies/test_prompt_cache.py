"""The frozen-backbone fast path: prompt tokens computed once per prompt give the reference path's loss and
gradients exactly, and the backbone no longer sees a cached prompt."""

import pytest
import torch

from lerobot_jept import JEPTConfig
from lerobot_jept.policies.components.perceiver import PerceiverIO
from lerobot_jept.policies.jept.modeling_jept import PROMPT_ID, PROMPT_MASK, PROMPT_VIDEO
from lerobot_jept.policies.vid2robot.configuration_vid2robot import Vid2RobotConfig
from tests.lerobot_jept.policies.test_policy import build_policy, mixed_batch


def loss_and_grads(policy, batch):
    policy.zero_grad()
    loss, _ = policy.forward(batch)
    loss.backward()
    return loss.detach(), {n: p.grad.clone() for n, p in policy.named_parameters() if p.grad is not None}


def count_backbone_frames(policy) -> list[int]:
    seen = []
    policy.model.backbone.register_forward_hook(lambda module, args, out: seen.append(args[0].shape[0]))
    return seen


@pytest.mark.parametrize("policy_type", ["jept", "vid2robot"])
def test_cached_prompt_tokens_give_the_reference_loss_and_gradients(tiny_build, policy_type):
    overrides = dict(freeze_backbone=True, backbone_chunk_size=5)
    overrides["config_cls"] = Vid2RobotConfig if policy_type == "vid2robot" else JEPTConfig
    reference, pre, _ = build_policy(tiny_build, prompt_token_cache=False, **overrides)
    fast, _, _ = build_policy(tiny_build, prompt_token_cache=True, **overrides)
    fast.load_state_dict(reference.state_dict())
    torch.manual_seed(0)
    batch = pre(mixed_batch(reference.config, size=6))
    assert PROMPT_ID in batch and (batch[PROMPT_ID] >= 0).all()
    reference.train(), fast.train()

    torch.manual_seed(1)
    loss_ref, grads_ref = loss_and_grads(reference, batch)
    seen = count_backbone_frames(fast)
    frames_per_pass = []
    for _ in range(2):  # cold (fills the cache), then warm
        before = sum(seen)
        torch.manual_seed(1)
        loss, grads = loss_and_grads(fast, batch)
        frames_per_pass.append(sum(seen) - before)
        torch.testing.assert_close(loss, loss_ref, rtol=0, atol=1e-6)
        assert grads.keys() == grads_ref.keys()
        for name, grad in grads.items():
            torch.testing.assert_close(grad, grads_ref[name], rtol=1e-5, atol=1e-6, msg=name)
    unique = {int(i): int(m.sum()) for i, m in zip(batch[PROMPT_ID], batch[PROMPT_MASK], strict=True)}
    prompt_frames = sum(unique.values())  # each bank prompt once, however many samples share it
    obs_frames = batch[reference.config.image_key].shape[:2].numel()
    first, second = frames_per_pass
    assert first - second == prompt_frames  # the warm step sends no prompt frame through the backbone
    assert second == obs_frames


def test_a_given_prompt_is_cached_by_its_content(tiny_build):
    policy, _, _ = build_policy(tiny_build, freeze_backbone=True)
    seen = count_backbone_frames(policy)
    video = torch.rand(2, 3, 3, 64, 64)
    with torch.no_grad():
        a = policy.model.encode_prompt(video, None)
        b = policy.model.encode_prompt(video.clone(), None)
        other = policy.model.encode_prompt(video.flip(0), None)
    assert torch.equal(a, b) and torch.equal(other, a.flip(0))
    assert seen == [3, 3]  # only the first call ran the backbone, once per prompt
    policy.model.clear_prompt_cache()
    with torch.no_grad():
        policy.model.encode_prompt(video, None)
    assert seen == [3, 3, 3, 3]
    with torch.no_grad():  # other backbone weights loaded: the cached tokens are not theirs
        policy.model.backbone.load_state_dict(
            {k: v + 0.01 for k, v in policy.model.backbone.state_dict().items()}
        )
        policy.model.encode_prompt(video, None)
    assert seen == [3, 3, 3, 3, 3, 3]


def test_a_trained_backbone_never_uses_the_cache(tiny_build):
    policy, _, _ = build_policy(tiny_build, freeze_backbone=False, prompt_token_cache=True)
    seen = count_backbone_frames(policy)
    video = torch.rand(1, 3, 3, 64, 64)
    with torch.no_grad():
        policy.model.encode_prompt(video, None, torch.tensor([7]))
        policy.model.encode_prompt(video, None, torch.tensor([7]))
    assert seen == [3, 3]


def test_a_batch_norm_backbone_in_training_is_never_chunked(tiny_build):
    # chunks would change batch norm's batch statistics: the small configuration's ResNet takes every frame of a
    # step in one pass in training (a prompt told apart from its scene-mate's by them: test_prompt.py)
    frames = torch.rand(5, 3, 64, 64)
    whole, _, _ = build_policy(tiny_build, freeze_backbone=False, backbone_chunk_size=1000)
    policy, _, _ = build_policy(tiny_build, freeze_backbone=False, backbone_chunk_size=2)
    seen = count_backbone_frames(policy.train())
    with torch.no_grad():
        torch.testing.assert_close(
            policy.model.backbone_tokens(frames), whole.train().model.backbone_tokens(frames)
        )
        assert seen == [5]
        policy.eval()  # running statistics: each frame on its own, so chunks are exact
        torch.testing.assert_close(
            policy.model.backbone_tokens(frames), whole.eval().model.backbone_tokens(frames)
        )
    assert seen == [5, 2, 2, 1]


def test_prompt_cache_dtype_is_checked():
    with pytest.raises(ValueError, match="prompt_cache_dtype must be"):
        JEPTConfig.small(prompt_cache_dtype="int8", device="cpu")


def test_chunked_checkpointed_prompt_frames_give_the_same_embedding_and_gradients():
    from lerobot_jept.policies.components.encoders import PromptVideoEncoder

    sizes = dict(num_latents=8, num_queries=2, heads=2, ff_dim=32, dropout=0.0)
    torch.manual_seed(0)
    whole = PromptVideoEncoder(24, sizes, sizes, dim=16, max_frames=6, chunk_size=1000)
    chunked = PromptVideoEncoder(24, sizes, sizes, dim=16, max_frames=6, chunk_size=4, checkpointing=True)
    chunked.load_state_dict(whole.state_dict())
    tokens = torch.randn(3, 6, 5, 24)
    mask = torch.ones(3, 6, dtype=torch.bool)
    mask[1, 4:] = False
    outputs = []
    for encoder in (whole, chunked):
        encoder.zero_grad()
        out = encoder(tokens.bfloat16() if encoder is chunked else tokens.bfloat16().float(), mask)
        out.square().sum().backward()
        outputs.append((out.detach(), {n: p.grad.clone() for n, p in encoder.named_parameters()}))
    (ref, ref_grads), (out, grads) = outputs
    torch.testing.assert_close(out, ref, rtol=1e-5, atol=1e-6)
    for name, grad in grads.items():
        torch.testing.assert_close(grad, ref_grads[name], rtol=1e-4, atol=1e-6, msg=name)


def test_control_keeps_the_prompt_embedding_until_a_parameter_changes(tiny_build):
    policy, _, _ = build_policy(tiny_build, freeze_backbone=True)
    policy.eval()
    calls = []
    policy.model.prompt_encoder.register_forward_hook(lambda *args: calls.append(1))
    video, ids = torch.rand(2, 3, 3, 64, 64), torch.tensor([5, 6])
    with torch.no_grad():
        first = policy.model.encode_prompt(video, None, ids)
        again = policy.model.encode_prompt(video, None, ids)
        assert len(calls) == 1 and again is first
        policy.model.prompt_encoder.video_perceiver.queries.add_(1.0)  # what an optimizer step does
        changed = policy.model.encode_prompt(video, None, ids)
    assert len(calls) == 2 and not torch.allclose(changed, first)
    policy.train()
    with torch.no_grad():
        policy.model.encode_prompt(video, None, ids)
    assert len(calls) == 3  # training never reuses an embedding


def test_bank_prompts_travel_as_uint8_and_give_the_float_prompts_loss(tiny_build):
    """The preprocessor hands bank prompts over as their decoded uint8 frames (a quarter of float32's memory
    and transfer); the policy converts them chunk by chunk to exactly the frames a float prompt carries."""
    policy, pre, _ = build_policy(
        tiny_build, freeze_backbone=True, prompt_token_cache=False, backbone_chunk_size=5
    )
    torch.manual_seed(0)
    batch = pre(mixed_batch(policy.config, size=4))
    video = batch[PROMPT_VIDEO]
    assert video.dtype == torch.uint8 and video.max() > 1
    as_float = {**batch, PROMPT_VIDEO: video.float() / 255}
    policy.train()
    losses = []
    for given in (batch, as_float):
        torch.manual_seed(1)
        losses.append(loss_and_grads(policy, given))
    torch.testing.assert_close(losses[0][0], losses[1][0], rtol=0, atol=0)
    for name, grad in losses[0][1].items():
        torch.testing.assert_close(grad, losses[1][1][name], rtol=0, atol=0, msg=name)


@pytest.mark.slow  # compiling takes two to four minutes on a 2-core CPU
def test_compiled_blocks_give_the_eager_loss_gradients_and_actions(tiny_build):
    # the paper's recipe: the action head on the predicted h_t+1, the graphs this check was sized for
    eager, pre, post = build_policy(tiny_build, freeze_backbone=True, recipe="paper")
    compiled, _, _ = build_policy(tiny_build, freeze_backbone=True, compile_model=True, recipe="paper")
    compiled.load_state_dict(eager.state_dict())
    assert compiled.state_dict().keys() == eager.state_dict().keys()  # checkpoints are the eager model's
    units = {
        n for n, m in compiled.model.named_modules() if getattr(m, "_compiled_call_impl", None) is not None
    }
    perceivers = {n for n, m in compiled.model.named_modules() if isinstance(m, PerceiverIO)}
    assert perceivers and perceivers <= units  # each Perceiver-IO whole
    assert not any(n.startswith("backbone") or any(n.startswith(f"{p}.") for p in perceivers) for n in units)
    torch.manual_seed(0)
    batch = pre(mixed_batch(eager.config, size=6))
    eager.eval(), compiled.eval()  # no dropout: the two draw their masks from different generators
    loss_ref, grads_ref = loss_and_grads(eager, batch)
    loss, grads = loss_and_grads(compiled, batch)
    torch.testing.assert_close(loss, loss_ref, rtol=1e-5, atol=1e-5)
    assert grads.keys() == grads_ref.keys()
    for name, grad in grads.items():
        torch.testing.assert_close(grad, grads_ref[name], rtol=1e-4, atol=1e-5, msg=name)

    obs = {k: v[:, -1] if k in ("observation.image", "observation.state") else v for k, v in batch.items()}
    with torch.no_grad():
        for policy in (eager, compiled):
            policy.reset()
        actions = [post(policy.select_action(obs)) for policy in (eager, compiled)]
    torch.testing.assert_close(actions[1], actions[0])


def test_compile_mode_is_checked():
    with pytest.raises(ValueError, match="compile_mode must be one of"):
        JEPTConfig.small(compile_mode="fast", device="cpu")


def test_rest_rates_invert_the_step_time_model():
    """On step times made from the bench's model (the backbone at one rate, the rest at another), the rates come
    back, and the rest's needed rate gives exactly the goal."""
    from benchmarks.bench_paper_scale import rest_rates

    frames, prompt_frames, per_frame = 18, 128, 33.7
    vit = {True: frames * per_frame, False: (frames + prompt_frames) * per_frame}
    rest = {
        ("encoder", True): 289.0,
        ("encoder", False): 286.0,
        ("others", True): 578.0,
        ("others", False): 575.0,
    }

    def model(vit_rate: float, rest_rate: float) -> tuple[dict, dict]:
        flops = {(c, p): vit[c] + rest[p, c] for c in (False, True) for p in ("encoder", "others")}
        times = {(c, p): vit[c] / vit_rate + rest[p, c] / rest_rate for c, p in flops}
        return times, flops

    times, flops = model(160.0, 100.0)
    rate, measured, needed = rest_rates(times, flops, (vit[True], vit[True] / 160.0), frames, prompt_frames)
    assert rate == pytest.approx(100.0) and measured == pytest.approx(100.0 / 160.0)
    times, _ = model(160.0, needed * 160.0)
    speedup = sum(v for (c, _), v in times.items() if not c) / sum(v for (c, _), v in times.items() if c)
    assert speedup == pytest.approx(5.0)
    # past the frames' ratio the goal is out of reach at any rate
    assert rest_rates(times, flops, (vit[True], 1.0), frames, prompt_frames=3 * frames)[2] == float("inf")
