"""Command-line options generated from a spec dataclass (roco_env.flags.SpecFlags)."""

from __future__ import annotations

import argparse
import dataclasses
from dataclasses import dataclass

import pytest

from roco_env.flags import SpecFlags
from roco_env.schema import ConfigError, spec


@dataclass(frozen=True)
class Inner:
    depth: int = spec(2, low=0)


@dataclass(frozen=True)
class Options:
    steps: int = spec(5, low=1, doc="steps to run")
    rate: float = spec(0.5, low=0.0, high=1.0, high_open=True, doc="a share")
    mode: str = spec("fast", choices=("fast", "slow"), doc="how")
    label: str | None = spec(None, doc="a name")
    enabled: bool = spec(True, doc="switch")
    extent: tuple[float, float] = spec((-1.0, 1.0), doc="low and high, m")
    names: tuple[str, ...] = spec(("a",), doc="some names")
    sizes: list[int] = spec([1, 2], doc="some sizes")
    inner: Inner = dataclasses.field(default_factory=Inner)


FLAGS = SpecFlags(Options, "tool", required=("label",), aliases={"--off": ("enabled", False)})


def parse(*argv: str) -> Options:
    parser = argparse.ArgumentParser(prog="tool")
    FLAGS.add_to(parser)
    return FLAGS.parse(parser.parse_args(["--label", "x", *argv]))


def test_options_not_given_keep_the_defaults_and_given_ones_take_their_types():
    assert parse() == Options(label="x")
    got = parse("--steps", "7", "--rate=0.25", "--mode", "slow", "--no-enabled",
                "--extent", "-3", "4.5", "--names", "b", "c", "--sizes", "3")
    assert got == Options(steps=7, rate=0.25, mode="slow", label="x", enabled=False,
                          extent=(-3.0, 4.5), names=("b", "c"), sizes=[3])
    assert parse("--off").enabled is False and parse("--enabled").enabled is True


def test_values_are_checked_by_the_dataclass_spec():
    with pytest.raises(ConfigError, match=r"tool: rate=1.0 is out of range; allowed "
                                          r"\[0.0, 1.0\)"):
        parse("--rate", "1")
    with pytest.raises(ConfigError, match=r"tool: steps=0 is out of range; allowed \[1, inf\)"):
        parse("--steps", "0")


@pytest.mark.parametrize("argv", [["--mode", "medium"], ["--steps", "many"],
                                  ["--extent", "1"], []])
def test_what_the_parser_cannot_read_is_a_usage_error(argv, capsys):
    parser = argparse.ArgumentParser(prog="tool")
    FLAGS.add_to(parser)
    with pytest.raises(SystemExit):
        parser.parse_args(argv + ([] if not argv else ["--label", "x"]))
    assert "tool: error" in capsys.readouterr().err


def test_help_says_what_a_field_is_its_default_and_what_is_allowed(capsys):
    parser = argparse.ArgumentParser(prog="tool")
    FLAGS.add_to(parser)
    text = " ".join(parser.format_help().split())
    assert "--rate RATE a share (default 0.5; [0.0, 1.0))" in text
    assert "--enabled, --no-enabled switch (default True)" in text
    assert "--sizes SIZES [SIZES ...] some sizes (default 1 2)" in text
    assert "--off the same as --no-enabled" in text
    assert "--depth" not in text and "--inner" not in text  # nested dataclasses: no option


def test_argv_reproduces_the_options():
    config = parse("--steps", "9", "--off", "--extent", "-2", "2", "--sizes", "4", "5")
    argv = FLAGS.argv(config)
    assert "--off" in argv and "--steps=9" in argv
    parser = argparse.ArgumentParser(prog="tool")
    FLAGS.add_to(parser)
    assert FLAGS.parse(parser.parse_args(argv)) == config
