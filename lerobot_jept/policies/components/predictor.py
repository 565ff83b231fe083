"""The video-conditioned causal predictor Psi_pred and its heads Gamma_obs, Gamma_act (Section 3.2.2), and DT*'s
transformer (the predictor without the joint embedding tokens)."""

import torch
from einops import rearrange, repeat
from torch import Tensor, nn
from torch.nn import functional as F

from lerobot_jept.policies.components.attention import (
    KV,
    CrossAttentionBlock,
    SelfAttentionStack,
    StepPositions,
)
from lerobot_jept.policies.components.token_groups import (
    DT_STAR_RULES,
    TokenGroup,
    attention_mask,
    dt_star_groups,
    group_slices,
    jept_groups,
)


class PromptedSequence(nn.Module):
    """What Psi_pred and DT*'s transformer share: input projections of the prompt and observation tokens, one
    type embedding per token kind (prompt, obs[, emb]), step positions and the Transformer stack."""

    def __init__(
        self,
        obs_dim: int,
        width: int,
        heads: int,
        ff_dim: int,
        layers: int,
        dropout: float,
        max_steps: int,
        tokens_per_step: int,
        num_kinds: int,
    ):
        super().__init__()
        self.prompt_in = nn.Linear(obs_dim, width)
        self.obs_in = nn.Linear(obs_dim, width)
        self.type_embed = nn.Parameter(torch.randn(num_kinds, width) * 0.02)
        self.positions = StepPositions(max_steps, tokens_per_step, width)
        self.transformer = SelfAttentionStack(width, heads, ff_dim, layers, dropout)

    def _obs_tokens(self, obs: Tensor) -> Tensor:
        """(B, k, N, D_in) -> (B, k, N, width) with step positions and the obs type."""
        return self.obs_in(obs) + self.positions(obs.shape[1]) + self.type_embed[1]

    def _with_prompt(self, prompt: Tensor | None, seq: Tensor, groups: list) -> tuple[Tensor, list]:
        """Prepend the prompt group (none during the warm-up)."""
        if prompt is None:
            return seq, groups
        seq = torch.cat([self.prompt_in(prompt) + self.type_embed[0], seq], dim=1)
        return seq, [TokenGroup("prompt", prompt.shape[1]), *groups]


class DTStarTransformer(PromptedSequence):
    """DT*: ``[E_prt | o_1, ..., o_k]`` under ``DT_STAR_RULES`` -> hidden states of the obs tokens (B, k, N,
    width). JEPT's predictor with the joint embedding prediction removed."""

    def __init__(self, obs_dim: int, width: int, **kwargs):
        super().__init__(obs_dim, width, num_kinds=2, **kwargs)

    def forward(self, prompt: Tensor | None, obs: Tensor) -> Tensor:
        k, n = obs.shape[1], obs.shape[2]
        seq = rearrange(self._obs_tokens(obs), "b k n d -> b (k n) d")
        seq, groups = self._with_prompt(prompt, seq, dt_star_groups(0, k, n))
        z = self.transformer(seq, mask=attention_mask(groups, DT_STAR_RULES).to(seq.device))
        return torch.stack([z[:, s] for s in group_slices(groups, "obs")], dim=1)


class CausalPredictor(PromptedSequence):
    """``Z = Psi_pred(E_prt, o_1, h_2, ..., o_k, h_{k+1})`` with the block-causal mask of the paper.

    Inputs: prompt (B, N_prt, D_in) or None (warm-up), obs tokens (B, k, N_obs, D_in), joint embeddings
    (B, k, N_obs, joint_dim) for h_2..h_{k+1}. Returns the hidden states of the obs and emb tokens,
    each (B, k, N_obs, width).
    """

    def __init__(self, obs_dim: int, joint_dim: int, width: int, **kwargs):
        super().__init__(obs_dim, width, num_kinds=3, **kwargs)
        self.emb_in = nn.Linear(joint_dim, width)

    def _sequence(self, prompt: Tensor | None, obs: Tensor, emb: Tensor) -> tuple[Tensor, list]:
        """Input tokens and groups; ``emb`` may lack the last step (k - 1 embeddings): its group is left out."""
        k, n = obs.shape[1], obs.shape[2]
        o = self._obs_tokens(obs)
        h = self.emb_in(emb) + self.positions(k)[: emb.shape[1]] + self.type_embed[2]
        missing = k - emb.shape[1]
        if missing:
            h = torch.cat([h, torch.zeros_like(o[:, -missing:])], dim=1)
        seq = rearrange(torch.stack([o, h], dim=2), "b k g n d -> b (k g n) d")
        groups = jept_groups(0, k, n)
        if missing:
            seq, groups = seq[:, :-n], groups[:-1]
        return self._with_prompt(prompt, seq, groups)

    def forward(self, prompt: Tensor | None, obs: Tensor, emb: Tensor) -> tuple[Tensor, Tensor]:
        seq, groups = self._sequence(prompt, obs, emb)
        z = self.transformer(seq, mask=attention_mask(groups).to(seq.device))
        z_obs = torch.stack([z[:, s] for s in group_slices(groups, "obs")], dim=1)
        z_emb = torch.stack([z[:, s] for s in group_slices(groups, "emb")], dim=1)
        return z_obs, z_emb

    def prompt_kv(self, prompt: Tensor | None) -> KV:
        """Control: every layer's keys and values of the prompt tokens. The prompt attends only to itself, so
        these are the same at every step of an episode: computed once, then passed to :meth:`last_obs_hidden`
        and :meth:`forward_last_step`. An empty list without a prompt (the warm-up's prediction)."""
        if prompt is None:
            return []
        return self.transformer.prefix_kv(self.prompt_in(prompt) + self.type_embed[0])

    def _after_prompt(self, prompt_kv: KV, obs: Tensor, emb: Tensor, last: int) -> tuple[Tensor, KV]:
        """The sequence after the prompt: its ``last`` tokens' outputs, and the keys and values of everything."""
        seq, groups = self._sequence(None, obs, emb)
        prompt = prompt_kv[0][0].shape[2] if prompt_kv else 0
        if prompt:
            groups = [TokenGroup("prompt", prompt), *groups]
        return self.transformer.forward_after(prompt_kv, seq, attention_mask(groups)[prompt:], last)

    def last_obs_hidden(self, prompt_kv: KV, obs: Tensor, emb_past: Tensor) -> Tensor:
        """Control: hidden states (B, N, width) of the o_t tokens, those of ``forward(prompt, obs, emb_past)``,
        after the prompt's cached keys and values (the last layer runs the o_t queries alone)."""
        return self._after_prompt(prompt_kv, obs, emb_past, obs.shape[2])[0]

    def forward_last_step(self, prompt_kv: KV, obs: Tensor, emb_past: Tensor, predict_emb) -> Tensor:
        """Control: hidden states (B, N, width) of the h_{t+1} tokens, h_{t+1} = ``predict_emb`` of the o_t
        hidden states. One pass over the sequence up to o_t after the prompt's cached keys and values, then the
        h_{t+1} group alone on the keys and values of everything before it (the earlier tokens never attend to
        it), instead of two full passes."""
        k, n = obs.shape[1], obs.shape[2]
        z_last, kv = self._after_prompt(prompt_kv, obs, emb_past, n)
        h_next = self.emb_in(predict_emb(z_last)) + self.positions(k)[-1] + self.type_embed[2]
        return self.transformer.extend(kv, h_next)


class ObservationHead(nn.Module):
    """Gamma_obs: MLP (LeakyReLU) from obs-token hidden states (..., width) to h_{t+1} tokens (..., joint_dim)."""

    def __init__(self, width: int, joint_dim: int, hidden_dim: int = 256, layers: int = 3):
        super().__init__()
        dims = [width] + [hidden_dim] * (layers - 1)
        blocks = []
        for d_in, d_out in zip(dims[:-1], dims[1:], strict=True):
            blocks += [nn.Linear(d_in, d_out), nn.LeakyReLU()]
        self.mlp = nn.Sequential(*blocks, nn.Linear(dims[-1], joint_dim))

    def forward(self, z_obs: Tensor) -> Tensor:
        return self.mlp(z_obs)


class ActionHead(nn.Module):
    """Gamma_act: one learnable query per action dimension cross-attends to the h_{t+1} hidden states.

    (B, k, N_obs, width) -> logits (B, k, action_dim, num_bins).
    """

    def __init__(
        self,
        width: int,
        action_dim: int,
        num_bins: int,
        dim: int = 256,
        heads: int = 4,
        layers: int = 2,
        ff_dim: int = 512,
        dropout: float = 0.0,
    ):
        super().__init__()
        self.queries = nn.Parameter(torch.randn(action_dim, dim) * 0.02)
        self.blocks = nn.ModuleList(
            CrossAttentionBlock(dim, heads, ff_dim, dropout, context_dim=width) for _ in range(layers)
        )
        self.out = nn.Sequential(nn.LayerNorm(dim), nn.Linear(dim, num_bins))

    def forward(self, z_emb: Tensor) -> Tensor:
        b, k = z_emb.shape[:2]
        context = rearrange(z_emb, "b k n d -> (b k) n d")
        q = repeat(self.queries, "a d -> bk a d", bk=b * k)
        for block in self.blocks:
            q = block(q, context)
        return rearrange(self.out(q), "(b k) a c -> b k a c", b=b)


class SelfStateInverseDynamics(nn.Module):
    """``idm_input="self_state"``: Gamma_state predicts the self-state change s_{t+1} - s_t (each dimension in
    units of its running RMS) from the o_t tokens' hidden states, and an MLP maps (s_t, change) to action logits;
    with ``history`` h > 0 it also reads the h observed changes into s_t (the arm lags its commanded motion, and
    how far it lags tells the action apart).

    With ``chunk`` H > 1 Gamma_state predicts the next H changes s_{t+1} - s_t, ..., s_{t+H} - s_{t+H-1} from
    o_t's tokens (an action chunk: :meth:`chunk_logits` reads an action from each).

    ``change_of`` (B, T + 1, S) states -> (B, T, S) scaled changes; ``past_changes`` (B, T, S) states ->
    (B, T, h * S); ``predict_changes`` (B, T, N, width) -> (B, T, H, S); ``forward`` (..., S) states, (..., S)
    changes and (..., h * S) past changes -> logits (..., action_dim, num_bins).
    """

    def __init__(
        self,
        width: int,
        state_dim: int,
        action_dim: int,
        num_bins: int,
        hidden_dim: int,
        layers: int,
        history: int = 0,
        chunk: int = 1,
    ):
        super().__init__()
        self.change_head = ObservationHead(width, chunk * state_dim, hidden_dim, layers)
        self.inverse = ObservationHead((2 + history) * state_dim, action_dim * num_bins, hidden_dim, layers)
        self.action_dim = action_dim
        self.history = history
        self.chunk = chunk
        self.register_buffer("scale", torch.ones(state_dim))
        self.register_buffer("scale_updates", torch.zeros((), dtype=torch.long))

    @torch.no_grad()
    def update_scale(self, state: Tensor, momentum: float = 0.01) -> None:
        """Training: move the per-dimension RMS of the changes towards this batch's (the first batch sets it)."""
        rms = (state[:, 1:] - state[:, :-1]).pow(2).mean((0, 1)).sqrt().clamp_min(1e-6)
        self.scale.copy_(rms if self.scale_updates == 0 else self.scale.lerp(rms, momentum))
        self.scale_updates += 1

    def change_of(self, state: Tensor) -> Tensor:
        return (state[:, 1:] - state[:, :-1]) / self.scale

    def past_changes(self, state: Tensor) -> Tensor:
        """(B, T, S) states -> (B, T, h * S): for each frame the h scaled changes into it, oldest first; zero
        where the window does not reach back (as at an episode's start, whose first frame LeRobot repeats)."""
        if self.history == 0:
            return state[..., :0]
        changes = F.pad(self.change_of(state), (0, 0, self.history, 0))  # (B, T - 1 + h, S)
        return rearrange(changes.unfold(1, self.history, 1), "b t s h -> b t (h s)")

    def predict_changes(self, z_obs: Tensor) -> Tensor:
        return rearrange(self.change_head(z_obs.mean(-2)), "... (h s) -> ... h s", h=self.chunk)

    def chunk_targets(self, state: Tensor, frame_ok: Tensor) -> tuple[Tensor, Tensor]:
        """(B, T + 1, S) states and (B, T) real-frame mask -> the scaled changes each of the T frames' chunk
        predicts (B, T, H, S) and which of them the window holds and are real (B, T, H): frame j's i-th is the
        change from frame j + i into j + i + 1."""
        pad = self.chunk - 1
        changes = F.pad(self.change_of(state), (0, 0, 0, pad)).unfold(1, self.chunk, 1)  # (B, T, S, H)
        ok = F.pad(frame_ok, (0, pad)).unfold(1, self.chunk, 1)  # (B, T, H)
        return rearrange(changes, "b t s h -> b t h s"), ok

    def chunk_logits(self, states: Tensor, changes: Tensor) -> Tensor:
        """Logits (B, H, action_dim, num_bins) of a_t .. a_{t+H-1} from the latest observed states, ending with
        s_t (B, >= h + 1, S), and the H predicted scaled changes after it (B, H, S): the i-th action is read
        from the state reached by the i changes before it, with the h changes (observed, then predicted) into
        that state."""
        steps = changes.shape[1]
        reached = states[:, -1:] + torch.cumsum(changes * self.scale, 1)[:, :-1]  # s_{t+1} .. s_{t+H-1}
        path = torch.cat([states, reached], 1)  # .. s_t .. s_{t+H-1}
        past = self.past_changes(path)[:, -steps:]
        return self(path[:, -steps:], changes, past if self.history else None)

    def forward(self, state: Tensor, change: Tensor, past: Tensor | None = None) -> Tensor:
        if past is None and self.history:
            raise ValueError(f"this inverse dynamics reads the {self.history} changes into s_t: pass `past`.")
        inputs = [state, change] if past is None else [state, change, past]
        logits = self.inverse(torch.cat(inputs, dim=-1))
        return rearrange(logits, "... (a c) -> ... a c", a=self.action_dim)
