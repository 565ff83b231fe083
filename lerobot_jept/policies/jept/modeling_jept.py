"""``JEPTPolicy``: the Joint Embedding Predictive Transformer as a LeRobot policy.

Training (paper Section 3.3, Algorithm 1): the k + 1 frames of a sample are tokenised frame by frame (backbone ->
Perceiver-IO + self-state token), the online temporal encoder gives the predictor's joint embedding inputs, the EMA
copy of the encoder gives the targets, the causal predictor runs over ``[E_prt | o_1, h_2, ..., o_k, h_{k+1}]`` and
``forward`` returns ``L_obs + c * L_act``. ``update()`` (called by LeRobot after every optimizer step) moves the EMA
targets and the step counter that drives the alternating phases and the prompt warm-up.

Control (end of Section 3.2.2): the new frame alone goes through the backbone and the Perceiver, the tokens of the
previous k - 1 frames and the prompt encoding are reused; the predictor predicts h_{t+1}, which is fed back in to
predict a_t.
"""

import copy
from collections import deque

import torch
import torch.nn.functional as F  # noqa: N812
from lerobot.utils.constants import OBS_STATE
from torch import Tensor, nn

from lerobot_jept.policies.base import (
    IGNORE_INDEX,
    PROMPT_ID,
    PROMPT_MASK,
    PROMPT_VIDEO,
    DiscreteActionPolicy,
    VisualPolicyNet,
    frame_mean,
    make_action_head,
    make_backbone,
    make_prompt_encoder,
    make_state_inverse_dynamics,
    make_tokenizer,
    transformer_kwargs,
)
from lerobot_jept.policies.components.alignment import PromptAlignment
from lerobot_jept.policies.components.encoders import JointEmbeddingEncoder
from lerobot_jept.policies.components.predictor import CausalPredictor, ObservationHead
from lerobot_jept.policies.jept.configuration_jept import JEPTConfig

__all__ = ["IGNORE_INDEX", "PROMPT_ID", "PROMPT_MASK", "PROMPT_VIDEO", "JEPT", "JEPTPolicy"]


class JointEmbeddingTarget(nn.Module):
    """The single-timestep encoder and the temporal encoder: Psi_obs without its frozen backbone."""

    def __init__(self, config: JEPTConfig, backbone_dim: int):
        super().__init__()
        self.tokenizer = make_tokenizer(config, backbone_dim)
        self.temporal = JointEmbeddingEncoder(
            config.perceiver_dim,
            config.temporal_dim,
            config.joint_embedding_dim,
            **transformer_kwargs(config, "temporal"),
            max_steps=config.n_obs_steps + 1,
            tokens_per_step=config.frame_perceiver_queries + 1,
        )


class NullPrompt(nn.Module):
    """The learned E_prt of "no prompt" for classifier-free guidance (``prompt_dropout``)."""

    def __init__(self, tokens: int, dim: int):
        super().__init__()
        self.tokens = nn.Parameter(torch.randn(tokens, dim) * 0.02)

    def forward(self, like: Tensor) -> Tensor:
        """The null prompt in the shape of the prompt encodings ``like`` (B, N_prt, D)."""
        return self.tokens.expand_as(like)


class JEPT(VisualPolicyNet):
    """The network: backbone, Psi_obs (online and EMA target), Psi_prt, Psi_pred, Gamma_obs, Gamma_act."""

    def __init__(self, config: JEPTConfig):
        super().__init__()
        self.config = config
        self.backbone = make_backbone(config)
        self.encoder = JointEmbeddingTarget(config, self.backbone.dim)
        self.target_encoder = copy.deepcopy(self.encoder).requires_grad_(False)
        self.prompt_encoder = make_prompt_encoder(config, self.backbone.dim)
        self.predictor = CausalPredictor(
            config.perceiver_dim,
            config.joint_embedding_dim,
            config.predictor_dim,
            **transformer_kwargs(config, "predictor"),
            max_steps=config.n_obs_steps,
            tokens_per_step=config.frame_perceiver_queries + 1,
        )
        self.obs_head = ObservationHead(
            config.predictor_dim,
            config.joint_embedding_dim,
            config.obs_head_hidden_dim,
            config.obs_head_layers,
        )
        # Gamma_act: on the h_{t+1} tokens' hidden states (the paper), or the self-state's inverse dynamics.
        self.action_head, self.state_dynamics = None, None
        if config.idm_input == "self_state":
            self.state_dynamics = make_state_inverse_dynamics(config)
        else:
            self.action_head = make_action_head(config, config.predictor_dim)

        # Behaviour cloning on the o_t hidden states (config.bc_head_weight): what control reads when it is on.
        self.bc_head = make_action_head(config, config.predictor_dim) if config.bc_head_weight > 0 else None

        # Classifier-free guidance (config.prompt_dropout): the learned E_prt of "no prompt".
        self.null_prompt = (
            NullPrompt(config.prompt_perceiver_queries, config.perceiver_dim)
            if config.prompt_dropout > 0
            else None
        )

        # Prompt-trajectory alignment (config.prompt_align_weight): projections of pooled E_prt and of pooled
        # target joint embeddings into one space, where prompts of a task meet that task's trajectories.
        self.prompt_align = PromptAlignment(config.perceiver_dim, config.joint_embedding_dim)

    def phase_modules(self) -> dict[str, list[nn.Module]]:
        """Algorithm 1's two phases: the joint embedding encoder, and every other trained component."""
        return {"encoder": [self.encoder], "others": [*self.prompt_modules(), *self.heads()]}

    def prompt_modules(self) -> list[nn.Module]:
        """The prompt encoder and what trains with it (the ``optimizer_lr_prompt`` group)."""
        null = [] if self.null_prompt is None else [self.null_prompt]
        return [self.prompt_encoder, self.prompt_align, *null]

    def heads(self) -> list[nn.Module]:
        """The predictor and its heads (the ``optimizer_lr_predictor`` group)."""
        gamma_act = self.action_head if self.state_dynamics is None else self.state_dynamics
        bc = [] if self.bc_head is None else [self.bc_head]
        return [self.predictor, self.obs_head, gamma_act, *bc]

    def frame_tokens(self, images: Tensor, state: Tensor) -> Tensor:
        return self.tokenize(self.encoder.tokenizer, self.backbone_tokens(images), state)

    def predict(
        self, prompt: Tensor | None, obs: Tensor, emb: Tensor, state: Tensor | None = None
    ) -> tuple[Tensor, Tensor | None, Tensor | None, Tensor | None]:
        """Predicted joint embeddings (B, k, N, J) from the obs tokens, action logits (B, k, A, bins), with
        ``idm_input="self_state"`` the predicted self-state changes (B, k, chunk_size, S) (else None), and with
        ``bc_head_weight`` the BC head's logits (B, k, A, bins) from the o_t hidden states (else None). With the
        self-state the inverse dynamics reads the real changes of ``state`` (B, k + 1, S), as the paper's reads
        the real h_{t+1} (no logits without it)."""
        z_obs, z_emb = self.predictor(prompt, obs, emb)
        pred_h = self.obs_head(z_obs)
        bc = None if self.bc_head is None else self.bc_head(z_obs)
        sd = self.state_dynamics
        if sd is None:
            return pred_h, self.action_head(z_emb), None, bc
        k = obs.shape[1]
        if state is None:
            return pred_h, None, sd.predict_changes(z_obs), bc
        logits = sd(state[:, :k], sd.change_of(state[:, : k + 1]), sd.past_changes(state[:, :k]))
        return pred_h, logits, sd.predict_changes(z_obs), bc

    @torch.no_grad()
    def update_target(self, decay: float) -> None:
        for target, online in zip(self.target_encoder.parameters(), self.encoder.parameters(), strict=True):
            target.lerp_(online.detach(), 1.0 - decay)


class JEPTPolicy(DiscreteActionPolicy):
    """Video-conditioned policy pi(a_t | o_{t-k+1..t}, prompt video) learned from demos and action-free videos."""

    config_class = JEPTConfig
    name = "jept"
    model_class = JEPT

    # Training ---------------------------------------------------------------------------------------------

    def get_optim_params(self) -> list[dict]:
        cfg, m = self.config, self.model
        return self.lr_groups(
            [
                (
                    "encoder",
                    cfg.optimizer_lr_encoder,
                    [m.encoder] + ([] if cfg.freeze_backbone else [m.backbone]),
                ),
                ("prompt", cfg.optimizer_lr_prompt, m.prompt_modules()),
                ("predictor", cfg.optimizer_lr_predictor, m.heads()),
            ]
        )

    @property
    def phase(self) -> str:
        if self.config.phase_schedule == "joint":
            return "joint"
        return ("encoder", "others")[(int(self.num_updates) // self.config.phase_steps) % 2]

    @property
    def prompt_active(self) -> bool:
        return int(self.num_updates) >= self.config.prompt_warmup_steps

    def _apply_phase(self) -> None:
        """Parameters outside the current phase get no gradient, so AdamW leaves them (and their moments)
        untouched: Algorithm 1's alternation inside LeRobot's single optimizer."""
        phase = self.phase
        for name, modules in self.model.phase_modules().items():
            for module in modules:
                module.requires_grad_(phase in ("joint", name))
        if not self.config.freeze_backbone:
            self.model.backbone.requires_grad_(phase in ("joint", "encoder"))

    def forward(self, batch: dict[str, Tensor], reduction: str = "mean") -> tuple[Tensor, dict]:
        cfg, m = self.config, self.model
        if self.training:
            self._apply_phase()
        k = cfg.n_obs_steps
        tokens, obs, h_in = self._encode_window(batch)
        targets = self._targets(batch, tokens)
        prompt = self.prompt(batch) if self.prompt_active else None
        if self.training and m.state_dynamics is not None:
            m.state_dynamics.update_scale(batch[OBS_STATE])
        prompt_in, kept = self._prompt_dropout(prompt)
        pred_h, logits, change, bc = m.predict(prompt_in, obs[:, :k], h_in, batch[OBS_STATE])
        loss_obs, dist, frame_ok = self._obs_loss(batch, pred_h, targets)

        # L_act (eq. 8): cross-entropy over the bins on labelled frames only (with ``idm_history`` h, not on the
        # window's first h frames, whose changes into them the window does not hold).
        loss_act, labelled = self.action_loss(logits, batch, first=cfg.idm_history)
        per_sample = loss_obs + cfg.action_loss_weight * loss_act
        extra, extra_info = self._prompt_losses(
            batch, prompt, obs[:, :k], h_in, targets, dist, frame_ok, kept
        )
        if change is not None:  # Gamma_state (idm_input=self_state), on each change the window holds for real
            target, ok = m.state_dynamics.chunk_targets(batch[OBS_STATE], frame_ok)
            error = (change - target).pow(2).mean(-1)  # (B, k, chunk_size)
            loss_state = frame_mean(error.flatten(1), ok.flatten(1))
            extra = extra + cfg.state_loss_weight * loss_state
            extra_info["loss_state"] = loss_state.mean().item()
            if cfg.change_consistency_weight:
                consistency = self._change_consistency(batch[OBS_STATE], change[:, :, 0], logits, ok[..., 0])
                extra = extra + cfg.change_consistency_weight * consistency
                extra_info["loss_consistency"] = consistency.mean().item()
        if bc is not None:
            loss_bc = self._bc_loss(batch, bc, logits, frame_ok)
            extra = extra + cfg.bc_head_weight * loss_bc
            extra_info["loss_bc"] = loss_bc.mean().item()
        per_sample = per_sample + extra
        info = {
            "loss_obs": loss_obs.mean().item(),
            "loss_act": self.labelled_mean(loss_act, labelled).item(),
            "labelled_fraction": labelled[..., 0].mean().item(),
            "phase_encoder": float(self.phase == "encoder"),
            "prompt_on": float(prompt is not None),
            **extra_info,
            **self.learning_rates(),
        }
        if reduction == "none":
            return per_sample, info
        loss_act_mean = self.labelled_mean(loss_act, labelled)
        return loss_obs.mean() + cfg.action_loss_weight * loss_act_mean + extra.mean(), info

    def _prompt_dropout(self, prompt: Tensor | None) -> tuple[Tensor | None, Tensor | float]:
        """In training, each sample's E_prt replaced by the null prompt with probability ``prompt_dropout``
        (classifier-free guidance) -> the predictor's prompt input and which samples kept theirs (B,)."""
        null = self.model.null_prompt
        if prompt is None or null is None or not self.training:
            return prompt, 1.0
        kept = (torch.rand(prompt.shape[0], device=prompt.device) >= self.config.prompt_dropout).float()
        return torch.where(kept[:, None, None].bool(), prompt, null(prompt)), kept

    def _prompt_losses(self, batch, prompt, obs, h_in, targets, dist, frame_ok, kept) -> tuple[Tensor, dict]:
        """The prompt terms that are not in the paper (``prompt_align_weight``, ``prompt_swap_weight``), per
        sample (B,). Both train the components of Algorithm 1's second phase only, so they are computed when
        that phase (or the joint schedule) is on and the prompt is past its warm-up; the swap term only on the
        samples that kept their prompt (``kept``, see ``prompt_dropout``)."""
        cfg, m = self.config, self.model
        zero = dist.new_zeros(dist.shape[0])
        if prompt is None or (self.training and self.phase == "encoder"):
            return zero, {}
        if cfg.prompt_align_weight == 0 and cfg.prompt_swap_weight == 0:
            return zero, {}
        task_ids = self.task_ids(batch, dist.shape[0], dist.device)
        extra, info = zero, {}
        if cfg.prompt_align_weight > 0:
            align = m.prompt_align(prompt, targets, task_ids, cfg.prompt_align_temperature)
            extra = extra + cfg.prompt_align_weight * align
            info["loss_prompt_align"] = align.item()
        if cfg.prompt_swap_weight > 0:
            # Each sample with the prompt of the next sample of another task (none: no term for it).
            other = task_ids[None, :] != task_ids[:, None]
            n = len(task_ids)
            steps = torch.arange(n, device=dist.device)
            swap_to = torch.where(other, (steps[None, :] - steps[:, None]) % n, n).argmin(-1)
            has_other = other.any(-1).float()
            pred_swapped = m.predict(prompt[swap_to], obs, h_in)[0]
            dist_swapped = torch.linalg.vector_norm(pred_swapped - targets, dim=-1).mean(-1)
            gap = frame_mean(dist_swapped - dist, frame_ok)
            swap = F.relu(cfg.prompt_swap_margin - gap) * has_other * kept
            extra = extra + cfg.prompt_swap_weight * swap
            info["loss_prompt_swap"] = swap.mean().item()
            info["prompt_swap_gap"] = gap.mean().item()
        return extra, info

    @torch.no_grad()
    def _targets(self, batch: dict[str, Tensor], tokens: Tensor) -> Tensor:
        """The EMA target encoder's joint embeddings h_2..h_{k+1} of the window's backbone tokens."""
        m = self.model
        target_obs = m.tokenize(m.target_encoder.tokenizer, tokens.detach(), batch[OBS_STATE])
        return m.target_encoder.temporal.context_embeddings(target_obs, first=1)

    def _change_consistency(self, state: Tensor, predicted: Tensor, real: Tensor, ok: Tensor) -> Tensor:
        """``change_consistency_weight``'s term -> per sample (B,): the cross-entropy of the action bins the
        inverse dynamics reads from the predicted changes (B, k, S) against its bin probabilities from the real
        ones (``real``, logits (B, k, A, bins)), over the frames whose next frame is real (``ok``, (B, k)) and
        whose past changes the window holds. The inverse dynamics runs on detached weights: the term trains
        what predicts the change, never what reads it."""
        sd, k = self.model.state_dynamics, predicted.shape[1]
        weights = {name: p.detach() for name, p in sd.named_parameters()}
        logits = torch.func.functional_call(
            sd, weights, (state[:, :k], predicted, sd.past_changes(state[:, :k]))
        )
        target = real.detach().softmax(-1).movedim(-1, 1)  # the bins as cross_entropy's class dimension
        ce = F.cross_entropy(logits.movedim(-1, 1), target, reduction="none").mean(-1)  # (B, k)
        return frame_mean(ce[:, sd.history :], ok[:, sd.history :])

    def _bc_loss(self, batch: dict[str, Tensor], bc: Tensor, inverse: Tensor, frame_ok: Tensor) -> Tensor:
        """``bc_head_weight``'s term -> per sample (B,): the BC head's cross-entropy (``bc``, logits (B, k, A,
        bins)) against the demos' actions and, on the frames without one whose next frame is real
        (``frame_ok``, (B, k)), the bins the inverse dynamics reads from the real next frame (``inverse``); not
        on the window's first ``idm_history`` frames, whose inverse dynamics lacks its past changes."""
        labels = self.action_labels(batch, bc.shape[:3])
        unlabelled = (labels == IGNORE_INDEX) & frame_ok.bool()[..., None]
        labels = torch.where(unlabelled, inverse.detach().argmax(-1), labels)
        return self.action_loss(bc, batch, first=self.config.idm_history, labels=labels)[0]

    def _obs_loss(self, batch: dict[str, Tensor], pred_h: Tensor, targets: Tensor) -> tuple[Tensor, ...]:
        """L_obs (eq. 7): the L2 distance per token between predicted and target joint embeddings, averaged
        over tokens and over the frames whose target is real -> per sample (B,), with the per-frame distances
        (B, k) and the real-frame mask (B, k)."""
        dist = torch.linalg.vector_norm(pred_h - targets, dim=-1).mean(-1)
        pad = batch.get(f"{self.config.image_key}_is_pad")
        frame_ok = torch.ones_like(dist) if pad is None else (~pad[:, 1:]).float()
        return frame_mean(dist, frame_ok), dist, frame_ok

    @torch.no_grad()
    def offline_outputs(self, batch: dict[str, Tensor]) -> dict[str, Tensor]:
        """On a preprocessed training-shaped batch (k + 1 frames): logits (B, A, bins) of a_t for the last
        context frame, ``control`` from the predicted h_{t+1} (with ``idm_input="self_state"``: the predicted
        self-state change; what ``select_action`` chooses) and ``inverse`` from the real next frame (the inverse
        dynamics alone); and ``loss_obs`` (B,)."""
        m, k = self.model, self.config.n_obs_steps
        tokens, obs, h_in = self._encode_window(batch)
        targets = self._targets(batch, tokens)
        prompt = self.prompt(batch) if self.prompt_active else None
        pred_h, logits, *_ = m.predict(prompt, obs[:, :k], h_in, batch[OBS_STATE])
        states = batch[OBS_STATE][:, :k]
        return {
            "control": self._control_logits(prompt, obs[:, :k], h_in[:, : k - 1], states)[:, 0],
            "inverse": logits[:, -1],
            "loss_obs": self._obs_loss(batch, pred_h, targets)[0],
        }

    @torch.no_grad()
    def observation_embedding(self, batch: dict[str, Tensor]) -> Tensor:
        """(B, joint_dim): the joint embedding of the last context frame over its k-frame context, averaged over
        tokens."""
        m, k = self.model, self.config.n_obs_steps
        images, state = self.camera_frames(batch)[:, :k], batch[OBS_STATE][:, :k]
        obs = m.tokenize(m.encoder.tokenizer, m.backbone_tokens(images), state)
        return m.encoder.temporal.context_embeddings(obs, first=k - 1)[:, 0].mean(1)

    def _encode_window(self, batch: dict[str, Tensor]) -> tuple[Tensor, Tensor, Tensor]:
        """A training-shaped window (k + 1 frames) -> backbone tokens, observation tokens and the predictor's
        joint embedding inputs h_2..h_{k+1} (each frame encoded over the frames up to it)."""
        m = self.model
        tokens = m.backbone_tokens(self.camera_frames(batch))
        obs = m.tokenize(m.encoder.tokenizer, tokens, batch[OBS_STATE])
        return tokens, obs, m.encoder.temporal.context_embeddings(obs, first=1)

    def update(self) -> None:
        """After every optimizer step: move the EMA targets, count the step."""
        self.model.update_target(self.config.ema_decay)
        super().update()

    # Control ----------------------------------------------------------------------------------------------

    def reset(self) -> None:
        super().reset()
        # The predictor's keys and values under the prompt and under the null prompt, with the prompt they are of.
        self._prompt_kv: dict[str, tuple] = {}
        self._action_queue: deque[Tensor] = deque()  # the rest of the chunk being executed (n_action_steps)

    @torch.no_grad()
    def select_action(self, batch: dict[str, Tensor], **kwargs) -> Tensor:
        """(B, action_dim) actions for the current observation (see ``control_actions``): the next action of
        the chunk being executed, else the first of a new chunk, of which the first ``n_action_steps`` are
        executed."""
        m = self.model
        prompt = self.episode_prompt(batch, self.prompt_active)
        obs = self.context_tokens(self.camera_frames(batch), batch[OBS_STATE])  # (B, k, N, D), every frame
        if self._action_queue:
            return self._action_queue.popleft()
        h_past = m.encoder.temporal.context_embeddings(obs, first=1)  # h_{t-k+2} .. h_t
        recent = list(self._frames)[-(self.config.idm_history + 1) :]  # what the inverse dynamics reads
        states = torch.stack([state for _, state in recent], 1)  # s_{t-h} .. s_t
        logits = self._control_logits(prompt, obs, h_past, states)
        self._action_queue.extend(
            self.control_actions(logits[:, i]) for i in range(self.config.n_action_steps)
        )
        return self._action_queue.popleft()

    def _control_logits(self, prompt: Tensor | None, obs: Tensor, h_past: Tensor, states: Tensor) -> Tensor:
        """Logits (B, H, A, bins) of a_t .. a_{t+H-1} (H = ``chunk_size``; 1 without a self-state inverse
        dynamics) from the obs tokens of o_{t-k+1..t} (B, k, N, D), h_{t-k+2..t} and the
        latest self-states, ending with s_t (B, >= idm_history + 1, S): the inverse dynamics of the predicted
        h_{t+1} or, with ``idm_input="self_state"``, of the self-state changes predicted from o_t's tokens. With
        ``prompt_guidance`` w, that prediction x (the change, else the logits) becomes x + w (x - x_null), x_null the one under the learned null prompt
        (``prompt_dropout``) or, without one, with no prompt (the prompt warm-up's prediction)."""
        cfg, m = self.config, self.model

        def predicted(p: Tensor | None, role: str) -> Tensor:
            if cfg.cache_frame_tokens:  # the prompt's keys and values, once per prompt (an episode's)
                cached = self._prompt_kv.get(role)
                if cached is None or cached[0] is not prompt:
                    cached = self._prompt_kv[role] = (prompt, m.predictor.prompt_kv(p))
                kv = cached[1]
                if m.bc_head is not None:
                    return m.bc_head(m.predictor.last_obs_hidden(kv, obs, h_past)[:, None])[:, 0]
                if m.state_dynamics is not None:
                    return m.state_dynamics.predict_changes(m.predictor.last_obs_hidden(kv, obs, h_past))
                hidden = m.predictor.forward_last_step(kv, obs, h_past, m.obs_head)
                return m.action_head(hidden[:, None])[:, 0]
            # the reference: full passes; for Gamma_act, h_{t+1} predicted by the first and fed into the second
            if m.bc_head is not None:
                return m.bc_head(m.predictor(p, obs, h_past)[0][:, -1:])[:, 0]
            if m.state_dynamics is not None:
                return m.state_dynamics.predict_changes(m.predictor(p, obs, h_past)[0][:, -1])
            placeholder = torch.zeros_like(obs[:, :1, :, : cfg.joint_embedding_dim])
            pred_h = m.predict(p, obs, torch.cat([h_past, placeholder], 1))[0]
            return m.predict(p, obs, torch.cat([h_past, pred_h[:, -1:]], 1))[1][:, -1]

        x = predicted(prompt, "prompt")
        if cfg.prompt_guidance and prompt is not None:
            null = None if m.null_prompt is None else m.null_prompt(prompt)
            x = x + cfg.prompt_guidance * (x - predicted(null, "null"))
        sd = m.state_dynamics
        return x[:, None] if sd is None or m.bc_head is not None else sd.chunk_logits(states, x)
