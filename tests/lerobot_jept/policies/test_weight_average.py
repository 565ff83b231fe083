"""weight_ema_decay: eval mode runs on an EMA of the trained weights, saved beside them; training resumes from them."""

import pytest
import torch
from safetensors.torch import load_file

from lerobot_jept import DTStarConfig, JEPTConfig, JEPTPolicy
from lerobot_jept.policies.jept.modeling_jept import PROMPT_VIDEO
from tests.lerobot_jept.policies.test_policy import build_policy, mixed_batch


def trained_weights(policy) -> dict[str, torch.Tensor]:
    return {n: p.detach().clone() for n, p in policy.model.named_parameters() if p.requires_grad}


def assert_weights(policy, expected: dict[str, torch.Tensor], exact: bool = False) -> None:
    params = dict(policy.model.named_parameters())
    for name, value in expected.items():
        if exact:
            assert torch.equal(params[name], value), name
        else:
            torch.testing.assert_close(params[name], value)


def test_eval_mode_runs_on_the_weight_average_and_training_resumes_from_the_trained_weights(
    tiny_build, tmp_path
):
    policy, pre, post = build_policy(tiny_build, weight_ema_decay=0.5)
    batch = pre(mixed_batch(policy.config, size=4))
    optimizer = torch.optim.AdamW(policy.get_optim_params(), lr=1e-2)
    average = trained_weights(policy)
    frozen = {n for n, p in policy.model.named_parameters() if not p.requires_grad}
    assert average and set(policy.weight_average.names) == set(average)
    assert any(n.startswith("target_encoder.") for n in frozen)  # JEPT's own EMA target is not averaged
    policy.train()
    for step in range(3):
        loss, _ = policy.forward(batch)
        optimizer.zero_grad()
        loss.backward()
        optimizer.step()
        policy.update()
        decay = min(0.5, (1 + step) / (10 + step))  # the warm-up: 0.1, 0.18, 0.25
        now = trained_weights(policy)
        average = {n: decay * average[n] + (1 - decay) * now[n] for n in now}
    trained = trained_weights(policy)
    assert any(not torch.equal(trained[n], average[n]) for n in trained)

    obs = {
        "observation.image": batch["observation.image"][:2, -1],
        "observation.state": batch["observation.state"][:2, -1],
        PROMPT_VIDEO: batch[PROMPT_VIDEO][:2],
    }
    policy.eval()
    policy.eval()  # twice: still the average, not swapped back
    assert_weights(policy, average)
    average = trained_weights(policy)
    policy.reset()
    actions = policy.select_action(obs)
    with pytest.raises(RuntimeError, match="policy.train"):
        policy.update()
    policy.save_pretrained(tmp_path / "in_eval")
    policy.train()
    assert_weights(policy, trained, exact=True)  # the exchange loses nothing
    policy.save_pretrained(tmp_path / "in_train")
    saved = load_file(tmp_path / "in_train" / "model.safetensors")
    assert {k for k in saved if k.startswith("weight_average.")} == {
        f"weight_average.{n.replace('.', '__')}" for n in average
    }
    in_eval = load_file(tmp_path / "in_eval" / "model.safetensors")
    assert all(torch.equal(in_eval[k], value) for k, value in saved.items())  # the same file in either mode

    for folder in ("in_eval", "in_train"):  # either mode's checkpoint loads the same policy
        loaded = JEPTPolicy.from_pretrained(tmp_path / folder)
        assert not loaded.training
        assert_weights(loaded, average, exact=True)
        loaded.reset()
        torch.testing.assert_close(loaded.select_action(obs), actions)
        loaded.train()  # what a resumed lerobot-train does: it trains on the trained weights
        assert_weights(loaded, trained, exact=True)
    without = JEPTPolicy.from_pretrained(tmp_path / "in_eval", weight_ema_decay=None)
    assert "weight_average" not in without._modules
    assert_weights(without, trained, exact=True)  # loaded without the average: the trained weights


def test_no_weight_average_by_default_and_a_bad_decay_names_the_range(tiny_build):
    policy, _, _ = build_policy(tiny_build)
    assert "weight_average" not in policy._modules
    assert not any(k.startswith("weight_average.") for k in policy.state_dict())
    with pytest.raises(ValueError, match=r"weight_ema_decay must be in \(0, 1\)"):
        JEPTConfig(weight_ema_decay=1.0)
    baseline, _, _ = build_policy(tiny_build, DTStarConfig, weight_ema_decay=0.99)
    assert baseline.weight_average.names  # an option of every policy type
