"""Every option of every entry point says in ``--help`` what it does, and its default when it has one.

Entry points: the ``codecsplat`` command line (every subcommand, every benchmark), the training entry points
``python -m train.*`` and the model report. An option whose default is a value (not None, not off) must name it in
its help text, either through argparse's ``%(default)s`` or in words ("default: all scenes").
"""

from __future__ import annotations

import argparse

import pytest

from codecsplat_warp import cli
from codecsplat_warp.bench import extreme
from codecsplat_warp.model import report
from train import codec_limits, curves, export, heldout, pack_scenes, self_render_bounds, stage1, stage2, validate

ENTRY_POINTS = {
    "codecsplat": cli.build_parser,
    "python -m codecsplat_warp.bench.extreme": extreme.build_parser,
    "python -m codecsplat_warp.model.report": report.build_parser,
    "python -m train.stage1": stage1.build_parser,
    "python -m train.stage2": stage2.build_parser,
    "python -m train.validate": validate.build_parser,
    "python -m train.export": export.build_parser,
    "python -m train.pack_scenes": pack_scenes.build_parser,
    "python -m train.heldout": heldout.build_parser,
    "python -m train.curves": curves.build_parser,
    "python -m train.codec_limits": codec_limits.build_parser,
    "python -m train.self_render_bounds": self_render_bounds.build_parser,
}


def parsers(parser: argparse.ArgumentParser, name: str):
    """(name, parser) of ``parser`` and of every subcommand below it."""
    yield name, parser
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            for sub_name, sub in action.choices.items():
                yield from parsers(sub, f"{name} {sub_name}")


def options_without_help(parser: argparse.ArgumentParser, name: str) -> list[str]:
    """The options and arguments of ``parser`` and its subcommands with no help, or with a default their help
    does not mention."""
    missing = []
    for command, sub in parsers(parser, name):
        for action in sub._actions:
            if isinstance(action, (argparse._HelpAction, argparse._SubParsersAction)):
                continue
            label = f"{command} {'/'.join(action.option_strings) or action.dest}"
            text = (action.help or "").strip()
            if not text or text == argparse.SUPPRESS:
                missing.append(f"{label}: no help")
            elif action.default is not None and action.default is not False and "default" not in text:
                missing.append(f"{label}: default {action.default!r} not named")
    return missing


@pytest.mark.parametrize("name", sorted(ENTRY_POINTS))
def test_every_option_says_what_it_does_and_its_default(name):
    assert options_without_help(ENTRY_POINTS[name](), name) == []


def test_the_check_finds_an_option_without_help():
    parser = argparse.ArgumentParser()
    parser.add_argument("--steps", type=int, default=5)
    parser.add_argument("--out", help="output folder")
    parser.add_argument("--seed", type=int, default=0, help="the seed")
    assert options_without_help(parser, "x") == ["x --steps: no help", "x --seed: default 0 not named"]


def test_every_help_text_renders():
    for name, build in ENTRY_POINTS.items():
        for command, parser in parsers(build(), name):
            assert parser.format_help(), command  # %-placeholders in help texts expand without error
