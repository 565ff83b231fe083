"""The causal predictor's token sequence as declared groups, and the attention mask derived from rules.

The sequence is ``[E_prt | o_{t-k+1}, h_{t-k+2}, ..., o_t, h_{t+1}]`` (paper, eq. 5). Each group is the block
of tokens of one item (the prompt, one observation, one joint embedding). The paper's rule (Appendix A.2):
a token attends to every token of a preceding group and to the tokens of its own group, never to a later
group. Rules are declared per (query kind, key kind) pair, in the style of Octo's block transformer, so a
variant is a new rule set, not new index arithmetic: DT* (``jept_dt_star``) drops the joint embedding tokens,
``[E_prt | o_{t-k+1}, ..., o_t]``, and its rule set never lets a token see an ``emb`` group.
"""

from dataclasses import dataclass
from enum import Enum

import torch
from torch import Tensor


class Attend(Enum):
    CAUSAL = "causal"  # keys of this kind in the same or an earlier group
    NEVER = "never"


@dataclass(frozen=True)
class TokenGroup:
    kind: str  # "prompt", "obs", "emb"
    length: int


# JEPT: every kind sees every kind causally (earlier groups and its own group).
JEPT_RULES: dict[tuple[str, str], Attend] = {
    (q, k): Attend.CAUSAL for q in ("prompt", "obs", "emb") for k in ("prompt", "obs", "emb")
}


# DT*: JEPT without the joint embedding prediction. Prompt and observation tokens, block-causal; no emb tokens.
DT_STAR_RULES: dict[tuple[str, str], Attend] = {
    (q, k): Attend.CAUSAL for q in ("prompt", "obs") for k in ("prompt", "obs")
}


def dt_star_groups(num_prompt_tokens: int, num_steps: int, tokens_per_step: int) -> list[TokenGroup]:
    """``[prompt | obs_1, obs_2, ..., obs_k]``; no prompt group when 0 tokens."""
    groups = [TokenGroup("prompt", num_prompt_tokens)] if num_prompt_tokens else []
    return groups + [TokenGroup("obs", tokens_per_step) for _ in range(num_steps)]


def jept_groups(num_prompt_tokens: int, num_steps: int, tokens_per_step: int) -> list[TokenGroup]:
    """``[prompt | obs_1, emb_2, obs_2, emb_3, ..., obs_k, emb_{k+1}]``; no prompt group when 0 tokens."""
    groups = [TokenGroup("prompt", num_prompt_tokens)] if num_prompt_tokens else []
    for _ in range(num_steps):
        groups += [TokenGroup("obs", tokens_per_step), TokenGroup("emb", tokens_per_step)]
    return groups


def attention_mask(groups: list[TokenGroup], rules: dict[tuple[str, str], Attend] = JEPT_RULES) -> Tensor:
    """(N, N) bool mask for ``nn.MultiheadAttention``-style APIs: True where attention is BLOCKED."""
    group_of = torch.cat([torch.full((g.length,), i) for i, g in enumerate(groups)])
    allowed = torch.zeros(len(group_of), len(group_of), dtype=torch.bool)
    for qi, qg in enumerate(groups):
        for ki, kg in enumerate(groups):
            rule = rules.get((qg.kind, kg.kind), Attend.NEVER)
            if rule is Attend.CAUSAL and ki <= qi:
                allowed[(group_of == qi)[:, None] & (group_of == ki)[None, :]] = True
    return ~allowed


def group_slices(groups: list[TokenGroup], kind: str) -> list[slice]:
    """Token index ranges of every group of ``kind``, in sequence order."""
    slices, start = [], 0
    for g in groups:
        if g.kind == kind:
            slices.append(slice(start, start + g.length))
        start += g.length
    return slices
