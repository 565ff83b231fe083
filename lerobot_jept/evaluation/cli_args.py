"""The checkpoint and dataset arguments the evaluation tools share (``--policy.*``, ``--dataset.*``)."""

import dataclasses
from dataclasses import dataclass


@dataclass
class PolicyArg:
    path: str = ""  # checkpoint folder (.../pretrained_model) or Hub repo id
    device: str | None = None
    # jept: the classifier-free guidance weight (default: the checkpoint's)
    prompt_guidance: float | None = None
    # every policy type: how control decodes the bin logits and smooths the actions (default: the checkpoint's)
    action_decoding: str | None = None
    action_smoothing: float | None = None

    def apply(self, policy_cfg) -> None:
        """The overrides given on the command line, onto the checkpoint's config."""
        if self.device:
            policy_cfg.device = self.device
        own = {f.name for f in dataclasses.fields(policy_cfg) if f.init}
        overrides = {
            name: getattr(self, name)
            for name in ("prompt_guidance", "action_decoding", "action_smoothing")
            if getattr(self, name) is not None
        }
        for name, value in overrides.items():
            if name not in own:
                raise ValueError(
                    f"--policy.{name} is a jept option; {self.path} is a {policy_cfg.type} checkpoint."
                )
            setattr(policy_cfg, name, value)
        if overrides:
            policy_cfg.__post_init__()  # the config's checks (guidance needs a prompt warm-up or prompt dropout)


@dataclass
class DatasetArg:
    repo_id: str = ""  # the suite: the builder's mix repo, ORG/NAME_mix; the probe: a labelled repo
    root: str | None = None
