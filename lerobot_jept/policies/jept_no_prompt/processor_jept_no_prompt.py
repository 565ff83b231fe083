"""``make_jept_no_prompt_pre_post_processors``: JEPT's pipeline (the bank's prompt videos reach the policy, which
ignores them)."""

from lerobot_jept.policies.jept.processor_jept import make_jept_pre_post_processors
from lerobot_jept.policies.jept_no_prompt.configuration_jept_no_prompt import JEPTNoPromptConfig


def make_jept_no_prompt_pre_post_processors(config: JEPTNoPromptConfig, dataset_stats=None, **kwargs):
    return make_jept_pre_post_processors(config, dataset_stats)
