"""Section 4.4's visual priors as ``--policy.vision_backbone`` choices: DINOv2 and SAM (timm), VideoMAE (Hugging
Face) and RAFT optical flow (torchvision), each loaded from a local weights file the test writes (random
weights), trained one step and run in control through the frozen fast path; bad weights files fail in one line
naming the file expected."""

import pytest
import torch
from safetensors.torch import save_file

from lerobot_jept.policies.components.backbone import (
    BackboneWeightsUnavailableError,
    SpatialBackbone,
    expected_weights,
)
from tests.lerobot_jept.policies.test_policy import build_policy, mixed_batch

SIZE = 64
PRIORS = {  # name -> tokens per frame at 64 px
    "vit_small_patch14_dinov2.lvd142m": 1 + (SIZE // 14) ** 2,
    "samvit_base_patch16.sa1b": (SIZE // 16) ** 2,
    "videomae_small": (SIZE // 16) ** 2,
    "raft_small": (SIZE // 8) ** 2,
}


def saved_weights(name: str, path) -> dict:
    """A freshly initialised backbone's weights, written where a user would put downloaded ones."""
    torch.manual_seed(1)
    state = SpatialBackbone(name, pretrained=False, freeze=True, image_size=SIZE).model.state_dict()
    state = {k: v.contiguous() for k, v in state.items()}
    file = path / f"{name.split('.')[0]}.safetensors"
    save_file(state, str(file))
    return state, file


@pytest.mark.slow
@pytest.mark.parametrize("name", list(PRIORS))
def test_prior_loads_its_weights_file_trains_and_controls_through_the_fast_path(tiny_build, tmp_path, name):
    state, file = saved_weights(name, tmp_path)
    policy, pre, _ = build_policy(
        tiny_build,
        vision_backbone=name,
        pretrained_backbone=True,
        backbone_weights_path=str(file),
        freeze_backbone=True,
    )
    backbone = policy.model.backbone
    for key, value in state.items():
        assert torch.equal(backbone.model.state_dict()[key], value), key
    assert backbone.num_tokens == PRIORS[name]
    frames = []
    backbone.register_forward_hook(lambda module, args, out: frames.append(args[0].shape[0]))

    torch.manual_seed(0)
    batch = pre(mixed_batch(policy.config, size=4))
    policy.train()
    for _ in range(2):  # the second step finds every prompt's tokens cached
        before = len(frames)
        loss, _ = policy.forward(batch)
        loss.backward()
        assert torch.isfinite(loss)
        seen = sum(frames[before:])
    assert seen == batch[policy.config.image_key].shape[:2].numel()  # observation frames only
    trained = [n for n, p in policy.named_parameters() if p.grad is not None]
    assert trained and not any(n.startswith("model.backbone.") for n in trained)

    policy.eval()
    policy.reset()
    obs = {k: batch[k][:1, 0] for k in (policy.config.image_key, "observation.state")}
    obs |= {k: batch[k][:1] for k in batch if k.startswith("observation.prompt")}
    with torch.no_grad():
        actions = [policy.select_action(obs) for _ in range(3)]
    assert all(a.shape == (1, 4) and torch.isfinite(a).all() for a in actions)


@pytest.mark.slow
@pytest.mark.parametrize("name", ["raft_small", "videomae_small"])
def test_temporal_prior_pairs_each_frame_with_the_one_before(tiny_build, name):
    policy, _, _ = build_policy(
        tiny_build, vision_backbone=name, pretrained_backbone=False, freeze_backbone=True
    )
    torch.manual_seed(0)
    video = torch.rand(2, 3, 3, SIZE, SIZE)
    with torch.no_grad():
        tokens = policy.model.backbone_tokens(video)
        backbone = policy.model.backbone
        for b in range(2):
            for t in range(3):
                before = video[b, max(t - 1, 0)]
                expected = backbone(video[b, t][None], before[None])[0]
                torch.testing.assert_close(tokens[b, t], expected, rtol=1e-4, atol=1e-4)
    assert not torch.allclose(tokens[:, 1], tokens[:, 0])


@pytest.mark.slow
@pytest.mark.parametrize("name", list(PRIORS))
def test_missing_or_mismatched_weights_file_names_the_file_expected(tmp_path, name):
    missing = tmp_path / "nowhere.safetensors"
    with pytest.raises(BackboneWeightsUnavailableError) as err:
        SpatialBackbone(name, pretrained=True, freeze=True, image_size=SIZE, weights_path=str(missing))
    message = str(err.value)
    assert "\n" not in message and str(missing) in message and "does not exist" in message
    assert expected_weights(name) in message

    other = "raft_small" if name != "raft_small" else "vit_small_patch14_dinov2.lvd142m"
    _, wrong = saved_weights(other, tmp_path)
    with pytest.raises(BackboneWeightsUnavailableError) as err:
        SpatialBackbone(name, pretrained=True, freeze=True, image_size=SIZE, weights_path=str(wrong))
    message = str(err.value)
    assert "\n" not in message and "does not fit" in message and expected_weights(name) in message


def test_expected_weights_name_the_download():
    assert "raft_small_C_T_V2" in expected_weights("raft_small")
    assert "huggingface.co/timm/vit_base_patch14_dinov2.lvd142m" in expected_weights(
        "vit_base_patch14_dinov2.lvd142m"
    )
    assert "huggingface.co/timm/samvit_base_patch16.sa1b" in expected_weights("samvit_base_patch16.sa1b")
    assert "MCG-NJU/videomae-base" in expected_weights("videomae_base")
