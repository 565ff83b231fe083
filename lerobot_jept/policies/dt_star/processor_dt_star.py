"""``make_jept_dt_star_pre_post_processors``: JEPT's pipeline (prompt video from the bank, action bins)."""

from lerobot_jept.policies.dt_star.configuration_dt_star import DTStarConfig
from lerobot_jept.policies.jept.processor_jept import make_jept_pre_post_processors


def make_jept_dt_star_pre_post_processors(config: DTStarConfig, dataset_stats=None, **kwargs):
    return make_jept_pre_post_processors(config, dataset_stats)
