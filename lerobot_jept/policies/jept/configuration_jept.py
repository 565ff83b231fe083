"""``JEPTConfig``: every hyperparameter of the paper's Tables 5-6, and the recipe (``--policy.recipe``) that sets
the options the paper does not have.

``recipe="paper"`` is the paper's method: its objective (L_obs + c L_act), Gamma_act on the predictor's h_{t+1}
hidden states, Algorithm 1's alternating schedule, no prompt guidance. ``recipe="plus"`` (the default) sets every
departure of this package's recipe at once (:data:`RECIPES`): inverse dynamics on the self-state
(``idm_input="self_state"``), the two prompt terms (``prompt_align_weight``, ``prompt_swap_weight``) and
classifier-free guidance at control (``prompt_guidance=1``). An option given explicitly overrides its recipe's
value; the checkpoint records the recipe and every value.

Values the paper leaves open, set here by guess and marked "not given by the paper" below: the EMA decay
(``ema_decay``), the prompt warm-up length (``prompt_warmup_steps``), the phase length of Algorithm 1
(``phase_steps``), and the reading of Table 6's "90" as training epochs.

Reading of Table 6 (its row labels are lost in the text we have): 90 epochs (``--steps`` in LeRobot), AdamW,
learning rates 3e-5 for the joint embedding encoder and 7e-5 for the prompt video encoder and for the causal
predictor with its heads, weight decay 1e-4, gradient clipping 1.0, 200 linear warm-up steps and c = 8 (c = 8 is
confirmed by Appendix C.2).

The options every policy type shares (inputs, backbone, Perceivers, predictor sizes, action bins, optimizer
groups, prompt bank, caches) are :class:`~lerobot_jept.policies.configuration.VideoPolicyConfig`'s. A small
configuration that trains on a 2-core CPU is :meth:`JEPTConfig.small`, also shipped as the lerobot-train config
file ``examples/configs/train_jept_small_cpu.json``.
"""

from dataclasses import dataclass

from lerobot.configs.policies import PreTrainedConfig

from lerobot_jept.policies.configuration import VideoPolicyConfig, check_idm_input

PHASE_SCHEDULES = ("alternate", "joint")
# The options each recipe sets, unless given explicitly. "paper": the paper's method; "plus": the departures that
# made tasks seen only as video executable in the simulator (README, "Differences from the paper").
RECIPES = {
    "paper": dict(
        idm_input="embedding",
        prompt_align_weight=0.0,
        prompt_swap_weight=0.0,
        prompt_dropout=0.0,
        prompt_guidance=0.0,
    ),
    "plus": dict(
        idm_input="self_state",
        prompt_align_weight=1.0,
        prompt_swap_weight=1.0,
        prompt_dropout=0.0,
        prompt_guidance=1.0,
    ),
}


@PreTrainedConfig.register_subclass("jept")
@dataclass
class JEPTConfig(VideoPolicyConfig):
    """Joint Embedding Predictive Transformer (paper Section 3, Appendix A): the shared options
    (:class:`~lerobot_jept.policies.configuration.VideoPolicyConfig`) and those of the joint embedding prediction,
    its objective, Algorithm 1's schedule and the recipe.

    Args:
        joint_embedding_dim, temporal_dim, temporal_heads, temporal_layers, temporal_ff_dim, temporal_dropout:
            the bi-directional temporal encoder (256, 512, 8, 2, 1024, 0.1).
        obs_head_hidden_dim, obs_head_layers: Gamma_obs, an MLP with LeakyReLU (256, 3).
        action_loss_weight: c in eq. 9 (8).
        recipe: ``"paper"`` or ``"plus"`` (default): the values of ``idm_input``, ``prompt_align_weight``,
            ``prompt_swap_weight``, ``prompt_dropout`` and ``prompt_guidance`` left unset (:data:`RECIPES`;
            ``plus`` guides only a training that has a prediction without the prompt: a prompt warm-up or
            prompt dropout).
        idm_input: what Gamma_act reads. "embedding" (the paper): the predictor's hidden states of the h_{t+1}
            tokens. "self_state" (not in the paper): a head Gamma_state predicts the self-state change
            s_{t+1} - s_t from the o_t tokens' hidden states (learned from demos and videos alike, with weight
            ``state_loss_weight``), and the inverse dynamics is an MLP from (s_t, s_{t+1} - s_t) to the action
            bins, trained on the demos' real changes and run on the predicted one. The self-state is the part of
            the observation whose change tells the action in every scene, so this inverse dynamics carries
            over to the video-only tasks (docs/results.md, "Inverse dynamics on the self-state").
        idm_history: with ``idm_input="self_state"`` (not in the paper), the observed self-state changes into
            s_t the inverse dynamics reads beside the next one (0: s_t and the next change only; at most
            ``n_obs_steps - 1``). The arm lags its commanded motion, so the change into s_t tells how far:
            ``jept-screen --history=1`` lifts the share of the video-only tasks' actions readable from the true
            changes by 5-6 points on both transfer builds (docs/results.md, "Screening levers").
        chunk_size, n_action_steps: with ``idm_input="self_state"`` (not in the paper), action chunks: Gamma_state
            predicts the next ``chunk_size`` H self-state changes from o_t's tokens (each trained on the window's
            frames whose window holds it, so H is at most ``n_obs_steps``), the inverse dynamics reads an action
            from each (a_{t+i} from the state the i predicted changes before it reach), and control executes the
            first ``n_action_steps`` of them before it predicts again (1 <= n_action_steps <= H; a control
            setting, ``--policy.n_action_steps`` at evaluation). 1 and 1: one change, one action per step.
        state_loss_weight: weight of Gamma_state's loss (mean squared error of the change, each dimension
            divided by its running RMS); used with ``idm_input="self_state"`` only.
        change_consistency_weight: with ``idm_input="self_state"`` (not in the paper; 0, off, by default), the
            weight of a term that trains Gamma_state in the measure control uses it in: the actions the inverse
            dynamics reads from the predicted change should be the ones it reads from the real change
            (cross-entropy against its own bin probabilities there), on every real frame, videos included.
            Its gradient reaches Gamma_state and what feeds it, not the inverse dynamics. The squared error
            alone fits the mean change, which can sit in another action's bins than any change the data hold.
        bc_head_weight: not in the paper (0, off, by default). A second action head, behaviour cloning on the
            predictor's hidden states of the o_t tokens (those that predict h_{t+1}, prompt in context), trained
            with this weight on the demos' actions and on the video frames' actions as the inverse dynamics
            reads them from the real next frame (its most likely bins, computed in the same step, as
            ``jept-relabel`` labels a mix for BC+IDM). With it, control reads this head, not the inverse
            dynamics of the predicted h_{t+1} or change. One action per step (``chunk_size`` 1).
        ema_decay: decay of the EMA target encoder (not given by the paper; I-JEPA's 0.996).
        phase_schedule: "alternate" (Algorithm 1: encoder-only phases and other-components phases) or "joint".
        phase_steps: optimizer steps per phase (Algorithm 1 alternates per epoch; its length in steps is not
            given by the paper: set frames / batch size for one epoch).
        prompt_warmup_steps: steps at the start during which E_prt is excluded from the predictor (A.4; the
            length is not given by the paper).
        prompt_align_weight, prompt_align_temperature: not in the paper. A supervised contrastive term that
            pulls each sample's E_prt (mean token, projected) towards the EMA joint embeddings of every sample
            of the same task in the batch and away from the other tasks' (InfoNCE, temperature 0.1). Without
            it, wherever the observation already identifies the task the objective gives E_prt no reason to
            vary, and training drives it to a constant (README, "Prompt conditioning"). 0 turns it off.
        prompt_swap_weight, prompt_swap_margin: not in the paper. Each sample is also predicted under the
            prompt of a sample of another task in the batch, and a hinge asks L_obs to be at least
            ``prompt_swap_margin`` higher under the wrong prompt, so the predictor must read the prompt. Both
            terms train only Algorithm 1's second phase (prompt encoder, predictor, heads) after the prompt
            warm-up. Both weights 0 is the paper's objective exactly.
        prompt_dropout, prompt_guidance: not in the paper; classifier-free guidance (Ho and Salimans, 2022) on
            the prompt. In training, each sample's E_prt is replaced by a learned null prompt with probability
            ``prompt_dropout``, so the predictor also learns what to do without a prompt. In control, the
            prediction x under the prompt (the self-state change with ``idm_input="self_state"``, else the
            action logits) becomes x + ``prompt_guidance`` * (x - x_null), x_null the prediction under the
            null prompt: what the prompt adds is amplified. Trained without dropout, x_null is the prediction
            without E_prt, as in the prompt warm-up (``prompt_warmup_steps``, the only time it was trained).
            0 and 0 is the paper; guidance can be set at evaluation (``--policy.prompt_guidance``).
    """

    joint_embedding_dim: int = 256
    temporal_dim: int = 512
    temporal_heads: int = 8
    temporal_layers: int = 2
    temporal_ff_dim: int = 1024
    temporal_dropout: float = 0.1
    obs_head_hidden_dim: int = 256
    obs_head_layers: int = 3
    action_loss_weight: float = 8.0
    recipe: str = "plus"
    idm_input: str | None = None  # None: the recipe's
    idm_history: int = 0
    chunk_size: int = 1
    n_action_steps: int = 1
    state_loss_weight: float = 1.0
    change_consistency_weight: float = 0.0
    bc_head_weight: float = 0.0
    ema_decay: float = 0.996
    phase_schedule: str = "alternate"
    phase_steps: int = 1000
    prompt_warmup_steps: int = 1000
    prompt_align_weight: float | None = None  # None: the recipe's
    prompt_align_temperature: float = 0.1
    prompt_swap_weight: float | None = None
    prompt_swap_margin: float = 0.5
    prompt_dropout: float | None = None
    prompt_guidance: float | None = None

    def __post_init__(self):
        super().__post_init__()
        if self.recipe not in RECIPES:
            raise ValueError(
                f"recipe must be one of {tuple(RECIPES)}, got {self.recipe!r}: pass --policy.recipe=paper (the "
                "paper's method) or --policy.recipe=plus (this package's recipe)."
            )
        unset = [name for name in RECIPES[self.recipe] if getattr(self, name) is None]
        for name in unset:
            setattr(self, name, RECIPES[self.recipe][name])
        if "prompt_guidance" in unset and not (self.prompt_dropout or self.prompt_warmup_steps):
            self.prompt_guidance = 0.0  # the recipe's guidance needs a prediction without the prompt
        if self.phase_schedule not in PHASE_SCHEDULES:
            raise ValueError(
                f"phase_schedule must be one of {PHASE_SCHEDULES}, got {self.phase_schedule!r}: "
                "pass --policy.phase_schedule=alternate (Algorithm 1) or joint."
            )
        check_idm_input(self.idm_input)
        k, value = self.n_obs_steps, lambda name: getattr(self, name)
        ranges = {  # option -> its lowest and highest value, those in words, why
            "idm_history": (0, k - 1, "0, n_obs_steps - 1", "changes into s_t the context holds"),
            "chunk_size": (1, k, "1, n_obs_steps", "changes a window holds after its first frame"),
            "n_action_steps": (1, self.chunk_size, "1, chunk_size", "a chunk's actions run per prediction"),
            "change_consistency_weight": (0.0, float("inf"), "0, inf", "a loss weight"),
            "bc_head_weight": (0.0, float("inf"), "0, inf", "a loss weight"),
        }
        for name, (low, high, bounds, why) in ranges.items():
            if not low <= value(name) <= high:
                raise ValueError(
                    f"{name} must be in [{bounds}] = [{low}, {high}] ({why}), got {value(name)}."
                )
        for name, off in (("idm_history", 0), ("chunk_size", 1), ("change_consistency_weight", 0.0)):
            if value(name) != off and self.idm_input != "self_state":
                raise ValueError(
                    f"{name}={value(name)} works with the self-state inverse dynamics only: add "
                    f"--policy.idm_input=self_state (or --policy.recipe=plus), or drop --policy.{name}."
                )
        if self.bc_head_weight and self.chunk_size != 1:
            raise ValueError(
                f"bc_head_weight={self.bc_head_weight} gives one action per step: drop --policy.chunk_size "
                f"(got {self.chunk_size}) or --policy.bc_head_weight."
            )
        if not 0.0 <= self.prompt_dropout < 1.0:
            raise ValueError(f"prompt_dropout is a probability in [0, 1), got {self.prompt_dropout}.")
        if self.prompt_guidance < 0:
            raise ValueError(f"prompt_guidance must be >= 0 (0: no guidance), got {self.prompt_guidance}.")
        if self.prompt_guidance and not (self.prompt_dropout or self.prompt_warmup_steps):
            raise ValueError(
                f"prompt_guidance={self.prompt_guidance} needs a prediction without the prompt, which this "
                "training never made (no prompt warm-up, no prompt dropout): train with --policy.prompt_dropout=P "
                "(e.g. 0.2), or pass --policy.prompt_guidance=0."
            )
        if self.phase_steps < 1:
            raise ValueError(f"phase_steps must be >= 1, got {self.phase_steps}.")
