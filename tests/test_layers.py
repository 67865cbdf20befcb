"""The layering rule (docs/architecture.md): lower layers never import higher ones.

Every ``roco_env`` module's imports of other ``roco_env`` modules, read from its source
(deferred imports inside functions included), are checked against the layer table.
"""

from __future__ import annotations

import ast
from pathlib import Path

import roco_env

PACKAGE = Path(roco_env.__file__).parent

# Bottom to top, as docs/architecture.md draws them; modules of one layer may import
# each other. ``__init__`` (the package's entry points) sits on top of env.
LAYERS = (
    ("schema", "stages", "flags"),
    ("scenario",),
    ("geometry", "batched_nms"),
    ("traffic",),
    ("noise",),
    ("sensing",),
    ("comm",),
    ("policies",),
    ("fusion",),
    ("metrics",),
    ("env", "action_modes", "observation_modes", "pipeline", "observation", "evaluation",
     "global_state", "render", "wrappers", "rollout", "registration", "attacks", "__init__"),
    ("training",),
    ("sweeps",),
    ("stress",),
    ("cli",),
    ("testing",),  # scenes for the tests and benchmarks: nothing that runs the env uses it
    ("benchmarks",),
)
LEVEL = {name: level for level, names in enumerate(LAYERS) for name in names}


def _top(path: Path) -> str:
    """The top-level module or package of the file at ``path`` (under PACKAGE)."""
    return path.relative_to(PACKAGE).parts[0].removesuffix(".py")


def _imported_tops(path: Path) -> set[str]:
    tops = set()
    for node in ast.walk(ast.parse(path.read_text(), str(path))):
        if isinstance(node, ast.ImportFrom):
            assert node.level == 0, f"{path}: relative import"
            names = [node.module or ""]
        elif isinstance(node, ast.Import):
            names = [alias.name for alias in node.names]
        else:
            continue
        tops.update(n.split(".")[1] for n in names if n.startswith("roco_env."))
    return tops


def test_every_module_has_a_layer():
    tops = {_top(path) for path in PACKAGE.rglob("*.py")}
    assert tops <= set(LEVEL), sorted(tops - set(LEVEL))


def test_lower_layers_never_import_higher_ones():
    breaches = [
        f"{path.relative_to(PACKAGE.parent)} ({_top(path)}) imports roco_env.{target}"
        for path in sorted(PACKAGE.rglob("*.py"))
        for target in _imported_tops(path)
        if LEVEL[target] > LEVEL[_top(path)]
    ]
    assert not breaches, "\n".join(breaches)
