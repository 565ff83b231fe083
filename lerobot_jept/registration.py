"""How the plugin registers itself with LeRobot without slowing down LeRobot's commands.

LeRobot imports every installed ``lerobot_policy_*`` distribution at the start of every command (train, eval,
record, calibrate, teleoperate, ...). Importing this plugin therefore does almost nothing: :func:`register`
asks for the policy types to be registered when ``lerobot.configs.policies`` (the registry they extend) is
imported, and the env types when ``lerobot.envs.configs`` is; if LeRobot has imported them already, as
``lerobot-train`` and ``lerobot-eval`` have, that happens at once. A command that never loads a policy or an
env (calibration, teleoperation) pays nothing, and no simulator is imported until an env is built.

The policy types are namespaced (``jept``, ``jept_idm``, ``jept_dt_star``, ``jept_vid2robot``, ``jept_no_prompt``,
``jept_lapo``). The baselines' earlier bare names (``idm``, ``dt_star``, ``vid2robot``) stay as aliases, so older
checkpoints and commands still work, but only while no other package owns them: a clash skips the alias with a
warning that names the fix instead of taking the whole plugin down.
"""

import importlib
import importlib.abc
import json
import logging
import os
import sys
import warnings
from collections.abc import Callable
from pathlib import Path

POLICY_CONFIG_MODULES = (
    "lerobot_jept.policies.jept.configuration_jept",
    "lerobot_jept.policies.idm.configuration_idm",
    "lerobot_jept.policies.dt_star.configuration_dt_star",
    "lerobot_jept.policies.vid2robot.configuration_vid2robot",
    "lerobot_jept.policies.jept_no_prompt.configuration_jept_no_prompt",
    "lerobot_jept.policies.lapo.configuration_lapo",
)
ENV_CONFIG_MODULE = "lerobot_jept.envs.configs"

# Older names of the baselines' policy types -> their namespaced names.
POLICY_TYPE_ALIASES = {"idm": "jept_idm", "dt_star": "jept_dt_star", "vid2robot": "jept_vid2robot"}

_pending: dict[str, list[Callable[[], None]]] = {}


class _AfterImport(importlib.abc.MetaPathFinder):
    """Runs the callbacks waiting on a module right after that module's code has run."""

    def find_spec(self, fullname, path, target=None):
        if fullname not in _pending:
            return None
        for finder in sys.meta_path:
            if finder is self or not hasattr(finder, "find_spec"):
                continue
            spec = finder.find_spec(fullname, path, target)
            if spec is not None:
                break
        else:
            return None
        loader = spec.loader
        if loader is None or not hasattr(loader, "exec_module"):
            return None
        exec_module = loader.exec_module

        def exec_then_run_callbacks(module):
            exec_module(module)
            _run_callbacks(fullname)

        loader.exec_module = exec_then_run_callbacks
        return spec


_finder = _AfterImport()


def _run_callbacks(module: str) -> None:
    for callback in _pending.pop(module, []):
        try:
            callback()
        except Exception:  # a failing plugin must not break LeRobot's own import
            logging.exception("lerobot_policy_jept could not register with LeRobot (%s)", callback.__name__)


def after_import(module: str, callback: Callable[[], None]) -> None:
    """Call ``callback`` once ``module`` is imported: now if it already is, else right after its import."""
    if module in sys.modules:
        callback()
        return
    _pending.setdefault(module, []).append(callback)
    if _finder not in sys.meta_path:
        sys.meta_path.insert(0, _finder)


def register_policies() -> None:
    """Import the policy configs (which registers their types) and add the baselines' older names."""
    from lerobot.configs.policies import PreTrainedConfig

    for module in POLICY_CONFIG_MODULES:
        importlib.import_module(module)
    known = PreTrainedConfig.get_known_choices()
    for alias, name in POLICY_TYPE_ALIASES.items():
        cls = known[name]
        if alias not in known:
            PreTrainedConfig.register_subclass(alias, cls)
        elif known[alias] is not cls:
            warnings.warn(
                f"Another package registers the policy type {alias!r}, so it is not an alias of "
                f'{name!r} in this environment: use --policy.type={name} (and "type": "{name}" in an older '
                "checkpoint's config.json).",
                stacklevel=2,
            )


def register_envs() -> None:
    importlib.import_module(ENV_CONFIG_MODULE)


def register_processor_steps(config) -> None:
    """Import the processor module of ``config``'s policy type, which registers its processor steps.

    Called when a config is created: LeRobot loads a saved processor pipeline by its steps' registered names
    without importing the policy's processor module first.
    """
    importlib.import_module(type(config).__module__.replace("configuration_", "processor_"))


def register() -> None:
    """Register the policy types, their processor steps and the env types with LeRobot (see the module doc)."""
    after_import("lerobot.configs.policies", register_policies)
    after_import("lerobot.envs.configs", register_envs)
    try:
        message = mix_warning(sys.argv)
    except Exception:  # a check that cannot read its inputs stays silent: it must never break a command
        message = None
    if message:
        warnings.warn(message, stacklevel=2)


MIX_MARKER = "observation.action_labelled"  # lerobot_jept.envs.spec.ACTION_LABELLED, without importing it


def mix_warning(argv: list[str]) -> str | None:
    """``lerobot-train`` of a policy type this package does not own on a mix of labelled and action-free
    episodes (a builder's or ``jept-mix``'s mix with video tasks): the warning to give, else None. Such a policy
    would learn the action-free frames' neutral actions as real ones. Reads the command line and the dataset's
    ``meta/info.json`` and ``meta/jept_build.json`` only (local files; nothing is imported)."""
    if not argv or "lerobot_train" not in Path(argv[0]).name.replace("-", "_"):
        return None
    args = dict(a[2:].split("=", 1) for a in argv[1:] if a.startswith("--") and "=" in a)
    config = {}
    if "config_path" in args and Path(args["config_path"]).is_file():
        config = json.loads(Path(args["config_path"]).read_text())
    policy = config.get("policy") or {}
    if "policy.path" in args and (Path(args["policy.path"]) / "config.json").is_file():
        policy = json.loads((Path(args["policy.path"]) / "config.json").read_text())
    policy_type = args.get("policy.type", policy.get("type"))
    if not policy_type or policy_type.startswith("jept") or policy_type in POLICY_TYPE_ALIASES:
        return None
    dataset = config.get("dataset") or {}
    repo_id = args.get("dataset.repo_id", dataset.get("repo_id"))
    root = args.get("dataset.root", dataset.get("root"))
    if not repo_id:
        return None
    home = Path(os.getenv("HF_LEROBOT_HOME", Path(os.getenv("HF_HOME", "~/.cache/huggingface")) / "lerobot"))
    meta = (Path(root).expanduser() if root else home.expanduser() / repo_id) / "meta"
    if not (meta / "info.json").is_file() or not (meta / "jept_build.json").is_file():
        return None
    build = json.loads((meta / "jept_build.json").read_text())
    mixed = build.get("repos", {}).get("mix") == repo_id and build.get("split", {}).get("video")
    if not mixed or MIX_MARKER not in json.loads((meta / "info.json").read_text()).get("features", {}):
        return None
    return (
        f"{repo_id} is a mix of labelled and action-free episodes ({MIX_MARKER}); --policy.type={policy_type} "
        "does not read that marker and would learn the action-free frames' neutral actions as real ones. "
        "Train it on the labelled repo alone (a build's ORG/NAME_demo, or jept-mix with --demo_repo_ids only), "
        "or train a policy that learns from action-free frames (--policy.type=jept)."
    )
