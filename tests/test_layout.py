"""The packages' import graph has no cycle (counting imports inside functions too)."""

import ast
import importlib
from pathlib import Path

ROOT = Path(__file__).parents[1]
PACKAGES = ("lerobot_jept", "dataset_builders")


def import_graph() -> dict[str, set[str]]:
    modules = {}
    for package in PACKAGES:
        for path in (ROOT / package).rglob("*.py"):
            name = ".".join(path.relative_to(ROOT).with_suffix("").parts).removesuffix(".__init__")
            modules[name] = path
    graph = {}
    for name, path in modules.items():
        targets = set()
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
                for alias in node.names:  # `from pkg import module` names the module itself
                    full = f"{node.module}.{alias.name}"
                    targets.add(full if full in modules else node.module)
            elif isinstance(node, ast.Import):
                targets.update(alias.name for alias in node.names)
        graph[name] = {t for t in targets if t in modules and t != name}
    return graph


def cycles(graph: dict[str, set[str]]) -> list[list[str]]:
    """Strongly connected components of more than one module (Tarjan)."""
    index, low, stack, on_stack, found = {}, {}, [], set(), []

    def visit(v: str) -> None:
        index[v] = low[v] = len(index)
        stack.append(v)
        on_stack.add(v)
        for w in graph[v]:
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in on_stack:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            component = []
            while True:
                w = stack.pop()
                on_stack.discard(w)
                component.append(w)
                if w == v:
                    break
            if len(component) > 1:
                found.append(sorted(component))

    for v in graph:
        if v not in index:
            visit(v)
    return found


def test_no_import_cycle():
    graph = import_graph()
    assert (
        len(graph) > 40
        and "lerobot_jept.evaluation.suite"
        in graph["lerobot_jept.study.plan"] | graph["lerobot_jept.evaluation.compare"]
    )
    assert cycles(graph) == []


def test_cycle_detection_finds_a_planted_cycle():
    assert cycles({"a": {"b"}, "b": {"c"}, "c": {"a"}, "d": {"a"}}) == [["a", "b", "c"]]


def test_lerobots_shape_one_folder_per_policy_type():
    """Each registered policy type has its own folder with its configuration, modeling and processor modules (the
    paths LeRobot derives from the config's module); the top level keeps only the plugin's entry."""
    from lerobot.configs.policies import PreTrainedConfig

    import lerobot_jept  # noqa: F401  (registers the types)
    from lerobot_jept.registration import POLICY_CONFIG_MODULES

    package = ROOT / "lerobot_jept"
    for module in POLICY_CONFIG_MODULES:
        importlib.import_module(module)
    types = [t for t in PreTrainedConfig.get_known_choices() if t.startswith("jept")]
    assert len(types) == len(POLICY_CONFIG_MODULES) == 6
    for name in types:
        config_module = PreTrainedConfig.get_choice_class(name).__module__
        folder = Path(*config_module.split(".")[:-1])
        stem = config_module.split(".")[-1].removeprefix("configuration_")
        assert folder.parent == Path("lerobot_jept/policies"), config_module
        for kind in ("configuration", "modeling", "processor"):
            assert (ROOT / folder / f"{kind}_{stem}.py").is_file(), (name, kind)
    top = {p.stem for p in package.glob("*.py")}
    assert top == {"__init__", "registration"}, top
    assert {p.name for p in package.iterdir() if p.is_dir() and p.name != "__pycache__"} == {
        "policies",
        "evaluation",
        "datasets",
        "study",
        "envs",
    }


def test_tests_mirror_the_packages():
    """Each folder of tests is a folder of the product (a package, a sub-package or examples/), so a module's
    tests are found where the module is."""
    folders = {p.parent for p in (ROOT / "tests").rglob("test_*.py")} - {ROOT / "tests"}
    assert len(folders) >= 7
    for folder in folders:
        assert (ROOT / folder.relative_to(ROOT / "tests")).is_dir(), folder
