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
    make_dt_star_transformer,
    make_prompt_encoder,
    make_tokenizer,
)
from lerobot_jept.policies.dt_star.configuration_dt_star import DTStarConfig


class DTStar(VisualPolicyNet):
    """Backbone, single-frame tokenizer, Psi_prt, the causal Transformer and Gamma_act."""

    def __init__(self, config: DTStarConfig):
        super().__init__()
        self.config = config
        self.backbone = make_backbone(config)
        self.tokenizer = make_tokenizer(config, self.backbone.dim)
        self.prompt_encoder = make_prompt_encoder(config, self.backbone.dim)
        self.transformer = make_dt_star_transformer(config)
        self.action_head = make_action_head(config, config.predictor_dim)

    def action_logits(self, prompt: Tensor, obs: Tensor) -> Tensor:
        """E_prt (B, N_prt, D) and obs tokens (B, k, N, D) -> logits (B, k, A, bins) of a_{t-k+1} .. a_t."""
        return self.action_head(self.transformer(prompt, obs))


class DTStarPolicy(ContextActionPolicy):
    """DT*: pi(a_t | o_{t-k+1..t}, prompt video) by behaviour cloning on labelled frames (L_act alone)."""

    config_class = DTStarConfig
    name = "jept_dt_star"
    model_class = DTStar

    def get_optim_params(self) -> list[dict]:
        m = self.model
        return self.prompted_lr_groups([m.transformer, m.action_head])
