"""Shapes through every component, the predictor's causality, and the backbone's pretrained loading."""

import pytest
import torch

from lerobot_jept.policies.components.backbone import BackboneWeightsUnavailableError, SpatialBackbone
from lerobot_jept.policies.components.encoders import (
    JointEmbeddingEncoder,
    ObservationTokenizer,
    PromptVideoEncoder,
)
from lerobot_jept.policies.components.perceiver import PerceiverIO
from lerobot_jept.policies.components.predictor import ActionHead, CausalPredictor, ObservationHead
from lerobot_jept.policies.components.token_groups import attention_mask, jept_groups

SMALL_PERCEIVER = dict(num_latents=8, num_queries=4, heads=2, ff_dim=64, dropout=0.0)
D, J, W = 32, 16, 40


def test_perceiver_compresses_any_length_to_its_queries():
    p = PerceiverIO(input_dim=24, dim=D, **SMALL_PERCEIVER)
    assert p(torch.randn(3, 50, 24)).shape == (3, 4, D)
    assert p(torch.randn(2, 7, 24)).shape == (2, 4, D)


def test_encoders_shapes():
    tok = ObservationTokenizer(backbone_dim=24, state_dim=18, perceiver=SMALL_PERCEIVER, dim=D)
    obs = tok(torch.randn(6, 17, 24), torch.randn(6, 18))
    assert obs.shape == (6, 5, D)  # N_obs = 4 queries + 1 state token
    enc = JointEmbeddingEncoder(
        D, D, J, heads=2, ff_dim=64, layers=1, dropout=0.0, max_steps=8, tokens_per_step=5
    )
    assert enc(obs.view(2, 3, 5, D)).shape == (2, 3, 5, J)
    assert enc.context_embeddings(obs.view(2, 3, 5, D)).shape == (2, 3, 5, J)
    prompt = PromptVideoEncoder(24, SMALL_PERCEIVER, {**SMALL_PERCEIVER, "num_queries": 6}, D, max_frames=10)
    mask = torch.tensor([[True] * 10, [True] * 4 + [False] * 6])
    assert prompt(torch.randn(2, 10, 17, 24), mask).shape == (2, 6, D)


def test_mask_follows_the_declared_rules():
    groups = jept_groups(num_prompt_tokens=2, num_steps=2, tokens_per_step=3)
    blocked = attention_mask(groups)
    assert blocked.shape == (2 + 2 * 2 * 3, 14)
    # prompt tokens see only the prompt; o_1 tokens see prompt + o_1 (own group), not h_2
    assert not blocked[0, :2].any() and blocked[0, 2:].all()
    assert not blocked[2, :5].any() and blocked[2, 5:].all()
    # the last h token sees everything
    assert not blocked[-1].any()


@pytest.mark.parametrize("with_prompt", [True, False])
def test_predictor_is_causal_by_perturbing_future_tokens(with_prompt):
    torch.manual_seed(0)
    pred = CausalPredictor(D, J, W, heads=2, ff_dim=64, layers=2, dropout=0.0, max_steps=8, tokens_per_step=5)
    prompt = torch.randn(1, 6, D) if with_prompt else None
    obs, emb = torch.randn(1, 4, 5, D), torch.randn(1, 4, 5, J)
    z_obs, z_emb = pred(prompt, obs, emb)
    assert z_obs.shape == z_emb.shape == (1, 4, 5, W)
    obs2, emb2 = obs.clone(), emb.clone()
    emb2[:, 2:] += 10.0  # h_4, h_5 change
    obs2[:, 3] += 10.0  # o_4 changes
    z_obs2, z_emb2 = pred(prompt, obs2, emb2)
    torch.testing.assert_close(z_obs2[:, :3], z_obs[:, :3])  # o_1..o_3 do not see h_4.. nor o_4
    torch.testing.assert_close(z_emb2[:, :2], z_emb[:, :2])  # h_2, h_3 unchanged
    assert not torch.allclose(z_obs2[:, 3], z_obs[:, 3])
    if with_prompt:
        z_obs3, _ = pred(prompt + 1.0, obs, emb)
        assert not torch.allclose(z_obs3[:, 0], z_obs[:, 0])  # everything sees the prompt


def test_heads_shapes():
    z = torch.randn(2, 3, 5, W)
    assert ObservationHead(W, J)(z).shape == (2, 3, 5, J)
    assert ActionHead(W, action_dim=4, num_bins=7, dim=16, heads=2, ff_dim=32)(z).shape == (2, 3, 4, 7)


def test_backbone_tokens_and_freezing():
    bb = SpatialBackbone("vit_tiny_patch16_224", pretrained=False, freeze=True, image_size=32)
    assert (bb.num_tokens, bb.dim) == (1 + 4, 192)
    out = bb(torch.rand(2, 3, 32, 32))
    assert out.shape == (2, 5, 192) and not out.requires_grad
    assert all(not p.requires_grad for p in bb.parameters())
    cnn = SpatialBackbone("resnet18", pretrained=False, freeze=False, image_size=64)
    assert cnn(torch.rand(1, 3, 64, 64)).shape == (1, 4, 512)


def test_pretrained_weights_load_through_timm_from_a_local_file(tmp_path):
    import timm
    from safetensors.torch import save_file

    source = timm.create_model("vit_tiny_patch16_224", pretrained=False, num_classes=0, img_size=32)
    save_file(source.state_dict(), tmp_path / "weights.safetensors")
    bb = SpatialBackbone(
        "vit_tiny_patch16_224", True, True, 32, weights_path=str(tmp_path / "weights.safetensors")
    )
    for key, value in source.state_dict().items():
        torch.testing.assert_close(bb.model.state_dict()[key], value)


def test_pretrained_weights_without_network_say_how_to_proceed(monkeypatch):
    monkeypatch.setenv("HF_HUB_OFFLINE", "1")
    with pytest.raises(
        BackboneWeightsUnavailableError, match="backbone_weights_path=PATH.*pretrained_backbone=false"
    ):
        SpatialBackbone("vit_tiny_patch16_224", pretrained=True, freeze=True, image_size=32)


def test_context_embeddings_see_only_frames_up_to_their_own():
    torch.manual_seed(0)
    enc = JointEmbeddingEncoder(
        D, 48, J, heads=2, ff_dim=64, layers=2, dropout=0.0, max_steps=8, tokens_per_step=5
    )
    obs = torch.randn(2, 4, 5, D)
    h = enc.context_embeddings(obs)
    obs2 = obs.clone()
    obs2[:, 2:] += 5.0
    h2 = enc.context_embeddings(obs2)
    torch.testing.assert_close(h2[:, :2], h[:, :2])  # frames 0, 1 do not see frames 2, 3
    assert not torch.allclose(h2[:, 2], h[:, 2])
    # frame j's embedding is the bi-directional encoding of the window 0..j
    torch.testing.assert_close(h[:, 2], enc(obs[:, :3])[:, 2], atol=1e-5, rtol=1e-5)
