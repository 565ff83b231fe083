"""``JEPTNoPromptConfig``: JEPT with its prompt replaced by a learned constant, the baseline that tells what the
prompt video contributes from what the scene and the observations give away."""

from dataclasses import dataclass

from lerobot.configs.policies import PreTrainedConfig

from lerobot_jept.policies.jept.configuration_jept import JEPTConfig

# JEPT options that act on the prompt, and so have nothing to act on here.
PROMPT_OPTIONS = ("prompt_align_weight", "prompt_swap_weight", "prompt_dropout", "prompt_guidance")


@PreTrainedConfig.register_subclass("jept_no_prompt")
@dataclass
class JEPTNoPromptConfig(JEPTConfig):
    """``--policy.type=jept_no_prompt``: JEPT's recipe, objective, sizes and schedule, but the predictor sees one
    learned E_prt (a constant of the prompt encoding's shape) for every sample, so whatever it does on a task
    comes from the scene and its observations, never from the prompt video. Trains with the same command as
    ``jept`` (the prompt bank is still read and ignored); a prompt given in control is ignored too. The prompt
    terms, prompt dropout and guidance have nothing to act on: the recipe's values are set to 0 and giving
    one is an error."""

    def __post_init__(self):
        given = {name: getattr(self, name) for name in PROMPT_OPTIONS if getattr(self, name) is not None}
        super().__post_init__()
        if any(given.values()):
            raise ValueError(
                f"jept_no_prompt has no prompt for {', '.join(f'--policy.{n}' for n, v in given.items() if v)} "
                "to act on: drop the option, or train --policy.type=jept."
            )
        for name in PROMPT_OPTIONS:
            setattr(self, name, 0.0)
