"""Every subcommand's --help is complete: a description of what it does, and a help text for
every option and argument (with its default, where it has one that is not obvious)."""

import argparse

import pytest

from ros_free_bridge.cli import build_parser


def all_parsers(parser, path=("dualflow-bridge",)):
    yield path, parser
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            for name, sub in action.choices.items():
                yield from all_parsers(sub, path + (name,))


PARSERS = dict((" ".join(path), p) for path, p in all_parsers(build_parser()))


def test_the_nested_commands_are_walked_too():
    assert {
        "dualflow-bridge demo",
        "dualflow-bridge retarget-check",
        "dualflow-bridge motion convert",
        "dualflow-bridge servo provision",
        "dualflow-bridge eval train-evaluator",
    } <= set(PARSERS)


@pytest.mark.parametrize("name", sorted(PARSERS))
def test_help_is_complete(name):
    parser = PARSERS[name]
    assert parser.description and len(parser.description.split()) >= 5, f"{name}: no description"
    missing = [
        a.option_strings[-1] if a.option_strings else a.dest
        for a in parser._actions
        if not isinstance(a, (argparse._HelpAction, argparse._SubParsersAction))
        and (not a.help or a.help == argparse.SUPPRESS)
    ]
    assert not missing, f"{name}: options without help text: {missing}"
    parser.format_help()  # formats (a bad %-placeholder in a help text raises here)
