"""Alignment losses between a prompt video and the robot's own frames.

- :class:`PromptAlignment`: supervised contrastive (SupCon) alignment of a pooled prompt embedding with a pooled
  trajectory embedding, same-task samples of the batch as positives. JEPT's ``prompt_align_weight`` term (the
  trajectory side is the EMA target, without gradient) and Vid2Robot's prompt/robot video contrastive loss (both
  sides learn).
- :func:`cycle_consistency_loss`: Vid2Robot's video alignment loss, temporal cycle consistency (Dwibedi et al.,
  2019, cycle-back classification) between the frames of the prompt and of the robot window.
"""

import torch
import torch.nn.functional as F  # noqa: N812
from torch import Tensor, nn


class PromptAlignment(nn.Module):
    """InfoNCE between the mean prompt token (projected) and the mean trajectory token (projected) of every
    sample in the batch, with all samples of the same task as positives (SupCon)."""

    def __init__(self, prompt_dim: int, joint_dim: int, dim: int = 128):
        super().__init__()
        self.prompt_proj = nn.Sequential(nn.LayerNorm(prompt_dim), nn.Linear(prompt_dim, dim))
        self.traj_proj = nn.Sequential(nn.LayerNorm(joint_dim), nn.Linear(joint_dim, dim))

    def forward(self, prompt: Tensor, targets: Tensor, task_ids: Tensor, temperature: float) -> Tensor:
        """prompt (B, N_prt, D), targets (B, k, N, J), task_ids (B,) -> scalar loss."""
        p = F.normalize(self.prompt_proj(prompt.mean(1)), dim=-1)
        t = F.normalize(self.traj_proj(targets.mean((1, 2))), dim=-1)
        log_prob = (p @ t.T / temperature).log_softmax(-1)
        positive = (task_ids[:, None] == task_ids[None, :]).float()
        return -((log_prob * positive).sum(-1) / positive.sum(-1)).mean()


def cycle_consistency_loss(
    robot: Tensor, prompt: Tensor, robot_ok: Tensor, prompt_ok: Tensor, temperature: float
) -> Tensor:
    """Per-sample TCC cycle-back classification loss (B,).

    robot (B, T, D) and prompt (B, N, D) per-frame embeddings; robot_ok (B, T) and prompt_ok (B, N) bool, False
    for padded frames. Each real robot frame finds its soft nearest neighbour in the prompt, which must cycle
    back to the same robot frame (cross-entropy over the real robot frames). Samples with fewer than two real
    robot frames give 0.
    """
    robot, prompt = F.normalize(robot, dim=-1), F.normalize(prompt, dim=-1)
    to_prompt = -torch.cdist(robot, prompt).square() / temperature  # (B, T, N)
    alpha = to_prompt.masked_fill(~prompt_ok[:, None, :], float("-inf")).softmax(-1)
    soft_nn = alpha @ prompt  # (B, T, D)
    back = -torch.cdist(soft_nn, robot).square() / temperature  # (B, T, T)
    back = back.masked_fill(~robot_ok[:, None, :], float("-inf"))
    target = torch.arange(robot.shape[1], device=robot.device).expand(robot.shape[0], -1)
    ce = F.cross_entropy(back.transpose(1, 2), target, reduction="none")  # (B, T)
    ce = ce.masked_fill(~robot_ok, 0.0)
    usable = (robot_ok.sum(-1) >= 2).float()
    return usable * ce.sum(-1) / robot_ok.sum(-1).clamp_min(1)
