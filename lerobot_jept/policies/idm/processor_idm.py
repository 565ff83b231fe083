"""``make_jept_idm_pre_post_processors``: LeRobot's standard steps and the action bins (the IDM takes no prompt)."""

from lerobot.processor.factory import make_default_policy_processor_steps, make_policy_processor_pipelines

from lerobot_jept.policies.idm.configuration_idm import IDMConfig
from lerobot_jept.policies.jept.processor_jept import JeptActionBinsStep


def make_jept_idm_pre_post_processors(config: IDMConfig, dataset_stats=None, **kwargs):
    s = make_default_policy_processor_steps(config, dataset_stats)
    config.fit_action_range(dataset_stats)
    bins = JeptActionBinsStep(config.num_action_bins, *config.action_bounds())
    return make_policy_processor_pipelines(
        input_steps=[s.rename_observations, s.add_batch_dim, s.to_device, s.normalize, bins],
        output_steps=[s.unnormalize, s.to_cpu],
    )
