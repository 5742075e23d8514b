"""The house in pipeline order: no module imports a module on a later floor.

Read from the source (ast, nothing imported), every import counts, those inside functions
included. Floors, lowest first; a module may import its own floor and the floors below:

0. base: `features.py` (the dataset's keys), `checkpointing.py`, `checks.py`, `device.py`,
   `locking.py`, `library_logs.py`, `training_loop.py`, `config_args.py`, `progress.py`:
   shared helpers that import nothing of the package, so that every stage can use them.
   `training_loop.py` and `checkpointing.py` stay here rather than in `training/`: the
   VQ-VAE trainer and collection use them too
1. `env/`: the simulator
2. `expert/`: the scripted expert (acts in the env)
3. `collection/`: demonstrations as a LeRobotDataset (runs the expert in the env)
4. `vqvae/`: encoders, latent caches and latent datasets, read from the demonstrations (the
   object-pixel check simulates episodes again through collection's public functions)
5. `publishing/`: Hub push/pull and the cards of demonstrations and latent datasets; above the
   stages it describes, below every stage that may want to publish what it made
6. `policy/`: what `lerobot-eval` loads (configuration, modeling, processor, IQL, the
   latent sampler)
7. `training/`: the fast trainer of `murm train` (driver, run folder, evaluator, seed stack,
   CUDA graph, learning curves)
8. `experiments/`: `murm reproduce` and `murm report`
9. `demo.py`: the body of `murm demo` (env, expert, collection); only the CLI uses it
10. `cli.py` and the package's `__init__.py` (importing `lerobot_murm` registers the env and
    policy types)
"""

import ast
from pathlib import Path

import pytest

PACKAGE = Path(__file__).resolve().parents[1] / "lerobot_murm"

FLOORS = [
    (
        "lerobot_murm.features",
        "lerobot_murm.checkpointing",
        "lerobot_murm.checks",
        "lerobot_murm.device",
        "lerobot_murm.locking",
        "lerobot_murm.library_logs",
        "lerobot_murm.training_loop",
        "lerobot_murm.config_args",
        "lerobot_murm.progress",
    ),
    ("lerobot_murm.env",),
    ("lerobot_murm.expert",),
    ("lerobot_murm.collection",),
    ("lerobot_murm.vqvae",),
    ("lerobot_murm.publishing",),
    ("lerobot_murm.policy",),
    ("lerobot_murm.training",),
    ("lerobot_murm.experiments",),
    ("lerobot_murm.demo",),
    ("lerobot_murm.cli", "lerobot_murm"),
]


def floor_of(module: str) -> int | None:
    """The floor of a module: that of the longest name in FLOORS that is it or a package holding it."""
    best, floor = "", None
    for level, names in enumerate(FLOORS):
        for name in names:
            if (module == name or module.startswith(name + ".")) and len(name) > len(best):
                best, floor = name, level
    return floor


def module_name(path: Path, package: Path = PACKAGE) -> str:
    parts = path.relative_to(package.parent).with_suffix("").parts
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def imported(source: str, module: str, is_package: bool, known: set[str]) -> list[tuple[int, str]]:
    """(line, module) of every import of the package in `source`; `from a import b` counts as
    `a.b` where `a.b` is a module, as `a` otherwise."""
    found = []
    for node in ast.walk(ast.parse(source)):
        if isinstance(node, ast.Import):
            found += [(node.lineno, alias.name) for alias in node.names]
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:  # relative: from the module's package, up level - 1 more
                package = module.split(".") if is_package else module.split(".")[:-1]
                package = package[: len(package) - (node.level - 1)]
                base = ".".join(package + ([base] if base else []))
            for alias in node.names:
                found.append((node.lineno, f"{base}.{alias.name}" if f"{base}.{alias.name}" in known else base))
    return [(line, name) for line, name in found if name == "lerobot_murm" or name.startswith("lerobot_murm.")]


def modules(package: Path = PACKAGE) -> dict[str, Path]:
    return {module_name(path, package): path for path in sorted(package.rglob("*.py"))}


def upward_imports(package: Path = PACKAGE) -> list[str]:
    found = modules(package)
    upward = []
    for module, path in found.items():
        for line, target in imported(path.read_text(), module, path.name == "__init__.py", set(found)):
            if floor_of(target) > floor_of(module):
                upward.append(
                    f"{path.relative_to(package.parent)}:{line}: {module} (floor {floor_of(module)}) "
                    f"imports {target} (floor {floor_of(target)})"
                )
    return upward


def test_every_module_has_a_floor():
    assert [m for m in modules() if floor_of(m) is None] == []


def test_no_module_imports_one_on_a_later_floor():
    upward = upward_imports()
    assert not upward, "imports pointing up the pipeline:\n" + "\n".join(upward)


@pytest.mark.parametrize(
    ("source", "upward"),
    [
        ("from lerobot_murm.policy.iql import DoubleQ\n", True),
        ("def f():\n    import lerobot_murm.experiments.report\n", True),  # inside a function too
        ("from lerobot_murm import publishing\n", True),  # a module named in `from package import`
        ("from ..publishing import card\n", True),  # relative
        ("from lerobot_murm.env import MurmEnv\nfrom lerobot_murm import features\n", False),
        ("from . import frames\n", False),
    ],
)
def test_the_walk_finds_an_upward_import(tmp_path, source, upward):
    package = tmp_path / "lerobot_murm"
    for name in (
        "__init__.py",
        "features.py",
        "env/__init__.py",
        "vqvae/__init__.py",
        "vqvae/frames.py",
        "publishing/__init__.py",
        "publishing/card.py",
        "policy/__init__.py",
        "policy/iql.py",
        "experiments/__init__.py",
        "experiments/report.py",
    ):
        (package / name).parent.mkdir(parents=True, exist_ok=True)
        (package / name).write_text("")
    (package / "vqvae" / "check.py").write_text(source)
    found = upward_imports(package)
    assert bool(found) == upward, found
    assert all(line.startswith("lerobot_murm/vqvae/check.py:") for line in found)
