"""The checkpoint and dataset arguments the evaluation tools share (``--policy.*``, ``--dataset.*``)."""

import dataclasses
from dataclasses import dataclass


@dataclass
class PolicyArg:
    path: str = ""  # checkpoint folder (.../pretrained_model) or Hub repo id
    device: str | None = None
    # jept: the classifier-free guidance weight (default: the checkpoint's)
    prompt_guidance: float | None = None

    def apply(self, policy_cfg) -> None:
        """The overrides given on the command line, onto the checkpoint's config."""
        if self.device:
            policy_cfg.device = self.device
        if self.prompt_guidance is not None:
            if "prompt_guidance" not in {f.name for f in dataclasses.fields(policy_cfg) if f.init}:
                raise ValueError(
                    f"--policy.prompt_guidance is a jept option; {self.path} is a {policy_cfg.type} checkpoint."
                )
            policy_cfg.prompt_guidance = self.prompt_guidance
            policy_cfg.__post_init__()  # the config's checks: guidance needs a prompt warm-up or prompt dropout


@dataclass
class DatasetArg:
    repo_id: str = ""  # the suite: the builder's mix repo, ORG/NAME_mix; the probe: a labelled repo
    root: str | None = None
