"""``DTStarPolicy``: DT*, behaviour cloning with JEPT's parts and no joint embedding prediction.

Training: the k context frames are tokenised frame by frame (backbone -> Perceiver-IO + self-state token), the
causal Transformer runs over ``[E_prt | o_{t-k+1}, ..., o_t]`` (``DT_STAR_RULES``), the action head reads a_j
from the o_j hidden states, and ``forward`` returns L_act on the labelled frames. Control: only the new frame is
encoded; the action of the last frame is taken.
"""

from torch import Tensor

from lerobot_jept.policies.base import (
    ContextActionPolicy,
    VisualPolicyNet,
    make_action_head,
    make_backbone,
    make_prompt_encoder,
    make_tokenizer,
    transformer_kwargs,
)
from lerobot_jept.policies.components.predictor import DTStarTransformer
from lerobot_jept.policies.dt_star.configuration_dt_star import DTStarConfig


class DTStar(VisualPolicyNet):
    """Backbone, single-frame tokenizer, Psi_prt, the causal Transformer and Gamma_act."""

    def __init__(self, config: DTStarConfig):
        super().__init__()
        self.config = config
        self.backbone = make_backbone(config)
        self.tokenizer = make_tokenizer(config, self.backbone.dim)
        self.prompt_encoder = make_prompt_encoder(config, self.backbone.dim)
        self.transformer = DTStarTransformer(
            config.perceiver_dim,
            config.predictor_dim,
            **transformer_kwargs(config, "predictor"),
            max_steps=config.n_obs_steps,
            tokens_per_step=config.frame_perceiver_queries + 1,
        )
        self.action_head = make_action_head(config, config.predictor_dim)

    def frame_tokens(self, images: Tensor, state: Tensor) -> Tensor:
        return self.tokenize(self.tokenizer, self.backbone_tokens(images), state)

    def action_logits(self, prompt: Tensor, obs: Tensor) -> Tensor:
        """E_prt (B, N_prt, D) and obs tokens (B, k, N, D) -> logits (B, k, A, bins) of a_{t-k+1} .. a_t."""
        return self.action_head(self.transformer(prompt, obs))


class DTStarPolicy(ContextActionPolicy):
    """DT*: pi(a_t | o_{t-k+1..t}, prompt video) by behaviour cloning on labelled frames (L_act alone)."""

    config_class = DTStarConfig
    name = "jept_dt_star"
    model_class = DTStar

    def get_optim_params(self) -> list[dict]:
        cfg, m = self.config, self.model
        return self.lr_groups(
            [
                ("encoder", cfg.optimizer_lr_encoder, self.encoder_modules()),
                ("prompt", cfg.optimizer_lr_prompt, [m.prompt_encoder]),
                ("predictor", cfg.optimizer_lr_predictor, [m.transformer, m.action_head]),
            ]
        )
