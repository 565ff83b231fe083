"""``IDMPolicy``: a_t = f(o_t, o_{t+1}) for the BC+IDM baseline, from the two frames' tokens or, with
``--policy.idm_input=self_state``, from the self-state and its change alone (VPT / BCO style). It labels recorded
frames offline (``jept-relabel``); it is not a controller, so ``select_action`` says so."""

from einops import rearrange
from lerobot.utils.constants import OBS_STATE
from torch import Tensor, nn

from lerobot_jept.policies.base import (
    DiscreteActionPolicy,
    VisualPolicyNet,
    make_action_head,
    make_backbone,
    make_state_inverse_dynamics,
    make_tokenizer,
    transformer_kwargs,
)
from lerobot_jept.policies.components.attention import SelfAttentionStack, StepPositions
from lerobot_jept.policies.idm.configuration_idm import IDMConfig


class IDM(VisualPolicyNet):
    """Backbone, single-frame tokenizer, a bi-directional Transformer over the two frames' tokens, Gamma_act;
    with ``idm_input="self_state"`` only an MLP from (s_t, s_t+1 - s_t) to the action bins."""

    def __init__(self, config: IDMConfig):
        super().__init__()
        self.config = config
        if config.idm_input == "self_state":
            self.state_dynamics = make_state_inverse_dynamics(config)
            return
        self.state_dynamics = None
        self.backbone = make_backbone(config)
        self.tokenizer = make_tokenizer(config, self.backbone.dim)
        width = config.predictor_dim
        self.inp = nn.Linear(config.perceiver_dim, width)
        self.positions = StepPositions(2, config.frame_perceiver_queries + 1, width)
        sizes = transformer_kwargs(config, "predictor")
        self.transformer = SelfAttentionStack(
            width, sizes["heads"], sizes["ff_dim"], sizes["layers"], sizes["dropout"]
        )
        self.action_head = make_action_head(config, width)

    def forward(self, images: Tensor | None, state: Tensor) -> Tensor:
        """Frames (B, 2, 3, H, W) and states (B, 2, S) of o_t, o_{t+1} -> logits (B, 1, A, bins) of a_t."""
        if self.state_dynamics is not None:
            sd = self.state_dynamics
            return sd(state[:, :1], sd.change_of(state))
        x = self.inp(self.frame_tokens(images, state)) + self.positions(2)
        z = self.transformer(rearrange(x, "b t n d -> b (t n) d"))
        return self.action_head(z[:, None])


class IDMPolicy(DiscreteActionPolicy):
    """Inverse dynamics model: the action bin of a_t from the transition (o_t, o_{t+1})."""

    config_class = IDMConfig
    name = "jept_idm"
    model_class = IDM

    def get_optim_params(self) -> list[dict]:
        cfg, m = self.config, self.model
        if m.state_dynamics is not None:
            return self.lr_groups([("predictor", cfg.optimizer_lr_predictor, [m.state_dynamics])])
        return self.lr_groups(
            [
                ("encoder", cfg.optimizer_lr_encoder, self.encoder_modules()),
                ("predictor", cfg.optimizer_lr_predictor, [m.inp, m.positions, m.transformer, m.action_head]),
            ]
        )

    def action_logits(self, batch: dict[str, Tensor]) -> Tensor:
        """Logits (B, A, bins) of a_t of a preprocessed batch (two frames per sample)."""
        if self.model.state_dynamics is not None:
            if self.training:
                self.model.state_dynamics.update_scale(batch[OBS_STATE])
            return self.model(None, batch[OBS_STATE])[:, 0]
        return self.model(self.camera_frames(batch), batch[OBS_STATE])[:, 0]

    def forward(self, batch: dict[str, Tensor], reduction: str = "mean") -> tuple[Tensor, dict]:
        loss, labelled = self.action_loss(self.action_logits(batch)[:, None], batch)
        mean = self.labelled_mean(loss, labelled)
        info = {
            "loss_act": mean.item(),
            "labelled_fraction": labelled[..., 0].mean().item(),
            **self.learning_rates(),
        }
        return (loss if reduction == "none" else mean), info

    def select_action(self, batch: dict[str, Tensor], **kwargs) -> Tensor:
        raise NotImplementedError(
            "An inverse dynamics model needs the next observation, so it cannot act: relabel a mix with "
            "`jept-relabel --policy.path=IDM_CHECKPOINT ...` and train --policy.type=jept_dt_star on the result."
        )
