"""``JEPTNoPromptPolicy``: JEPT whose prompt encoding is one learned constant (``--policy.type=jept_no_prompt``)."""

from torch import Tensor

from lerobot_jept.policies.jept.modeling_jept import JEPT, JEPTPolicy, NullPrompt
from lerobot_jept.policies.jept_no_prompt.configuration_jept_no_prompt import JEPTNoPromptConfig


class JEPTNoPrompt(JEPT):
    """JEPT's network with the learned constant E_prt (kept in ``null_prompt``, trained in the prompt group)."""

    def __init__(self, config: JEPTNoPromptConfig):
        super().__init__(config)
        self.null_prompt = NullPrompt(config.prompt_perceiver_queries, config.perceiver_dim)


class JEPTNoPromptPolicy(JEPTPolicy):
    """JEPT without its prompt: every sample, in training and in control, gets the same learned E_prt."""

    config_class = JEPTNoPromptConfig
    name = "jept_no_prompt"
    model_class = JEPTNoPrompt

    def prompt(self, batch: dict[str, Tensor]) -> Tensor:
        size = batch[self.config.image_key].shape[0]
        return self.model.null_prompt.tokens.expand(size, -1, -1)
