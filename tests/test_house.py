"""The repository explains itself: references point into it, never to files outside it."""

import re
from pathlib import Path

from conftest import run_python

ROOT = Path(__file__).resolve().parents[1]
TEXT = [p for folder in ("roco_env", "tests", "examples", "baselines", "docs")
        for p in sorted((ROOT / folder).rglob("*")) if p.suffix in (".py", ".md", ".yaml")]
TEXT += [ROOT / "README.md", ROOT / "Makefile", ROOT / "pyproject.toml"]
# Written in pieces so this file does not match itself.
OUTSIDE = re.compile("|".join([r"DESIGN" + r"\.md", r"\.\./" + "shared", r"\bissue" + r" \d+",
                               r"\bturn" + r" 2\b"]))
DOCS_LINK = re.compile(r"docs/([\w.-]+\.md)")


def test_no_reference_to_files_outside_the_repository():
    hits = [f"{path.relative_to(ROOT)}:{n}: {line.strip()}" for path in TEXT
            for n, line in enumerate(path.read_text().splitlines(), 1) if OUTSIDE.search(line)]
    assert not hits, hits


def test_every_docs_reference_exists():
    missing = {(str(p.relative_to(ROOT)), name) for p in TEXT
               for name in DOCS_LINK.findall(p.read_text())
               if not (ROOT / "docs" / name).is_file()}
    assert not missing


def test_docs_index_links_resolve():
    index = (ROOT / "docs" / "README.md").read_text()
    for name in re.findall(r"\]\(([\w.-]+\.md)\)", index):
        assert (ROOT / "docs" / name).is_file(), name


def test_the_env_does_not_import_the_policies():
    """The environment's module, really imported (its pipeline loaded), loads no policy."""
    probe = ("import sys, roco_env.env; "
             "print('roco_env.pipeline' in sys.modules, "
             "sorted(m for m in sys.modules if m.startswith('roco_env.policies')))")
    assert run_python(probe) == "True []"


def test_module_file_names_are_unique():
    names: dict[str, list[str]] = {}
    for path in sorted((ROOT / "roco_env").rglob("*.py")):
        if path.name not in ("__init__.py", "__main__.py"):
            names.setdefault(path.name, []).append(str(path.relative_to(ROOT)))
    shared = {name: paths for name, paths in names.items() if len(paths) > 1}
    assert not shared, shared


def test_the_command_line_builds_its_parser_without_torch():
    """Every `roco-env` command (`--help` included) builds the whole parser; its options,
    train-detector's too (roco_env.training.detector_config), come without torch."""
    probe = ("import sys; from roco_env.cli import build_parser; "
             "help = build_parser().format_help(); "
             "print('train-detector' in help, 'torch' in sys.modules)")
    assert run_python(probe) == "True False"
