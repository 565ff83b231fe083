"""``make_jept_lapo_pre_post_processors``: JEPT's pipeline (prompt video from the bank, action bins)."""

from lerobot_jept.policies.jept.processor_jept import make_jept_pre_post_processors
from lerobot_jept.policies.lapo.configuration_lapo import LAPOConfig


def make_jept_lapo_pre_post_processors(config: LAPOConfig, dataset_stats=None, **kwargs):
    return make_jept_pre_post_processors(config, dataset_stats)
