"""LAPO (``jept_lapo``): the latent action model learns from action-free transitions and never reads an action,
the decoder sees labelled frames only, and the mechanism works where it must."""

import torch
import torch.nn.functional as F  # noqa: N812

from lerobot_jept import LAPOConfig, LAPOPolicy
from lerobot_jept.policies.base import IGNORE_INDEX
from lerobot_jept.policies.components.latent_action import (
    FiniteScalarQuantizer,
    LatentActionDecoder,
    LatentActionModel,
)
from tests.lerobot_jept.policies.test_baselines import build


def test_quantizer_rounds_to_its_levels_and_passes_gradients():
    fsq = FiniteScalarQuantizer(5)
    z = torch.linspace(-4, 4, 101, requires_grad=True)
    values, indices = fsq(z)
    assert set(indices.tolist()) == {0, 1, 2, 3, 4}
    torch.testing.assert_close(values, fsq.values(indices))  # the forward value is the level's exactly
    values.sum().backward()
    assert (z.grad > 0).all()  # straight through the rounding


def test_latent_code_separates_two_action_free_motions_and_a_few_labels_decode_them():
    """Transitions of two motions (+x or +y at random positions, with noise), none labelled: the latent model
    gives each motion its own code; a decoder fitted on four labelled transitions of each maps the codes of
    held-out transitions to the right action."""
    g = torch.Generator().manual_seed(0)

    def transitions(n: int, motion: int) -> torch.Tensor:
        start = torch.rand(n, 2, generator=g)
        step = torch.zeros(n, 2)
        step[:, motion] = 0.1
        end = start + step + 0.005 * torch.randn(n, 2, generator=g)
        return torch.stack([start, end], dim=1)  # (n, 2, 2): o_t, o_t+1 as 2-D observation vectors

    torch.manual_seed(0)
    model = LatentActionModel(obs_dim=2, dims=2, levels=3, pixels=1, hidden_dim=64, layers=2)
    optim = torch.optim.Adam(model.parameters(), lr=3e-3)
    for _ in range(400):
        vectors = torch.cat([transitions(64, 0), transitions(64, 1)])
        model.update_scale(vectors, torch.ones(128, 1, dtype=torch.bool))
        _, _, error = model(vectors)
        optim.zero_grad()
        error.mean().backward()
        optim.step()

    model.eval()
    with torch.no_grad():
        codes = [model(transitions(200, motion))[1][:, 0] for motion in (0, 1)]
    majority = [torch.mode(c.unique(dim=0, return_inverse=True)[1]).values for c in codes]
    shares = [
        (c.unique(dim=0, return_inverse=True)[1] == m).float().mean()
        for c, m in zip(codes, majority, strict=True)
    ]
    assert min(shares) >= 0.9, shares  # each motion has one code ...
    first = [c.unique(dim=0, return_inverse=True)[0][m] for c, m in zip(codes, majority, strict=True)]
    assert not torch.equal(first[0], first[1])  # ... and they differ

    decoder = LatentActionDecoder(dims=2, state_dim=2, action_dim=1, num_bins=2, hidden_dim=32, layers=2)
    optim = torch.optim.Adam(decoder.parameters(), lr=1e-2)
    few = torch.cat([transitions(4, 0), transitions(4, 1)])
    labels = torch.tensor([0] * 4 + [1] * 4)
    with torch.no_grad():
        latent = model(few)[0][:, 0]
    for _ in range(200):
        loss = F.cross_entropy(decoder(latent, few[:, 0])[:, 0], labels)
        optim.zero_grad()
        loss.backward()
        optim.step()
    with torch.no_grad():
        accuracy = [
            (decoder(model(vectors)[0][:, 0], vectors[:, 0])[:, 0].argmax(-1) == motion).float().mean()
            for motion, vectors in enumerate([transitions(200, 0), transitions(200, 1)])
        ]
    assert min(accuracy) >= 0.9, accuracy


def latent_model_grads(policy, batch) -> dict[str, torch.Tensor]:
    policy.zero_grad()
    latent, _, error, valid = policy.transitions(batch)
    (error[valid].sum() + latent.sum()).backward()
    return {n: p.grad.clone() for n, p in policy.model.latent_model.named_parameters()}


def test_latent_model_never_reads_an_action(tiny_build):
    policy, batch = build(tiny_build, LAPOConfig)
    assert isinstance(policy, LAPOPolicy)
    k = policy.config.n_obs_steps
    assert batch["observation.image"].shape[1] == k + 1  # the context and the next frame
    policy.eval()
    reference = latent_model_grads(policy, batch)
    shuffled = {**batch, "action": batch["action"].flip(0)}
    without = {key: v for key, v in batch.items() if not key.startswith("action")}
    for other in (shuffled, without):
        grads = latent_model_grads(policy, other)
        for name, grad in grads.items():
            torch.testing.assert_close(grad, reference[name], msg=name)
    latent, indices, _, valid = policy.transitions(without)
    assert latent.shape == indices.shape == (8, k, policy.config.latent_dims) and valid.any()
    loss, info = policy.forward(without)  # no action anywhere: the decoder has nothing to learn
    assert torch.isfinite(loss) and info["loss_act"] == 0.0 and info["labelled_fraction"] == 0.0


def test_decoder_sees_only_labelled_frames(tiny_build):
    policy, batch = build(tiny_build, LAPOConfig)
    seen = []
    policy.model.decoder.register_forward_hook(lambda module, args, out: seen.append(args[0].shape[0]))
    loss, info = policy.forward(batch)
    labelled = (batch["action"] != IGNORE_INDEX).all(-1).reshape(-1)  # the bins step marks unlabelled frames
    pad = batch["observation.image_is_pad"]
    real = ~(pad[:, :-1] | pad[:, 1:]).reshape(-1)
    assert seen == [int((labelled & real).sum())] and 0 < seen[0] < labelled.numel()
    assert torch.isfinite(loss) and info["loss_act"] > 0 and info["loss_latent_forward"] > 0

    # the decoder's gradient comes from the labelled frames alone: an unlabelled sample adds none
    unlabelled = (batch["action"] == IGNORE_INDEX).all(-1).all(-1)
    assert unlabelled.any()
    policy.zero_grad()
    per_sample, _ = policy.forward(batch, reduction="none")
    per_sample[unlabelled].sum().backward()
    assert all(p.grad is None or not p.grad.any() for p in policy.model.decoder.parameters())


def test_lapo_acts_from_the_decoded_latent(tiny_build):
    policy, batch = build(tiny_build, LAPOConfig)
    policy.eval()
    k = policy.config.n_obs_steps
    obs = {key: batch[key][:, k - 1] for key in ("observation.image", "observation.state")}
    obs |= {key: batch[key] for key in ("observation.prompt_video", "observation.prompt_video_mask")}
    policy.reset()
    action = policy.select_action(obs)
    assert action.shape == (8, policy.config.resolved_action_dim)
    assert policy.offline_outputs(batch)["control"].shape == (8, policy.config.resolved_action_dim, 7)
