"""The command line's help: every flag and positional argument of every subcommand (nested ones
included) says what it is, the run arguments name the kinds of run each command reads, every
--device says its default, and a run path that does not exist is reported as "not found"."""

from __future__ import annotations

import argparse

import pytest

from warpnerf.cli import build_parser, main


def _commands(parser, path=()):
    """(command path, parser, its help in the parent's list) of the parser and every
    subcommand below it."""
    yield path, parser, None
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            helps = {a.dest: a.help for a in action._choices_actions}
            for name, sub in action.choices.items():
                yield (*path, name), sub, helps.get(name)
                for item in _commands(sub, (*path, name)):
                    if item[0] != (*path, name):
                        yield item


def _arguments():
    """(command, action) of every argument of every command, help and subcommands excluded."""
    for path, parser, _ in _commands(build_parser()):
        for action in parser._actions:
            if isinstance(action, (argparse._HelpAction, argparse._SubParsersAction)):
                continue
            yield " ".join(path), action


def _name(action) -> str:
    return "/".join(action.option_strings) or action.dest


def test_the_walk_reaches_nested_commands():
    paths = {" ".join(p) for p, _, _ in _commands(build_parser())}
    for cmd in ("train nerf", "train volsdf", "train sdf", "train box", "eval", "render", "mesh",
                "export", "view", "data", "bench", "demo"):  # fmt: skip
        assert cmd in paths, (cmd, sorted(paths))


def test_every_argument_and_subcommand_has_help():
    missing = [
        f"{cmd} {_name(a)}"
        for cmd, a in _arguments()
        if not (a.help or "").strip() or a.help == argparse.SUPPRESS
    ]
    missing += [" ".join(p) for p, _, h in _commands(build_parser()) if p and not (h or "").strip()]
    assert not missing, missing


def test_every_command_help_renders():
    """argparse expands ``%`` in help texts: a stray one breaks ``--help`` of its command."""
    for path, parser, _ in _commands(build_parser()):
        assert parser.format_help(), path


def test_every_device_flag_says_its_default():
    devices = [(cmd, a) for cmd, a in _arguments() if "--device" in a.option_strings]
    assert len(devices) >= 10, [c for c, _ in devices]
    for cmd, a in devices:
        text = " ".join(a.help.split())
        assert "default cpu" in text or "the run's" in text, (cmd, a.help)
        if a.default is not None:  # a fixed default: the help names it
            assert f"default {a.default}" in text, (cmd, a.help, a.default)


def test_train_lists_every_kind_of_run():
    (train_help,) = [h for p, _, h in _commands(build_parser()) if p == ("train",)]
    for kind in ("nerf", "volsdf", "sdf", "box"):
        assert kind in train_help.replace(",", " ").split(), (kind, train_help)


def _run_help(cmd: str) -> str:
    (action,) = [a for c, a in _arguments() if c == cmd and a.dest == "run"]
    return " ".join(action.help.split())


@pytest.mark.parametrize(
    "cmd,kinds,not_kinds",
    [
        ("eval", ["nerf", "volsdf"], ["box", " sdf"]),  # the NeRF runner's runs (any field)
        ("render", ["nerf", "volsdf"], ["box", " sdf"]),
        ("export", ["nerf", "volsdf"], ["box", " sdf"]),
        ("mesh", ["nerf", "volsdf", "sdf"], ["box"]),  # + neural SDFs from points
        ("view", ["nerf", "volsdf", "sdf", "box"], []),
    ],
)  # fmt: skip
def test_run_arguments_name_the_runs_each_command_reads(cmd, kinds, not_kinds):
    text = _run_help(cmd)
    for kind in kinds:
        assert kind in text, (cmd, kind, text)
    for kind in not_kinds:
        assert kind not in text, (cmd, kind, text)


@pytest.mark.parametrize(
    "argv",
    [
        ["eval", "{p}"],
        ["eval", "{p}", "--geometry", "materials"],
        ["render", "{p}"],
        ["mesh", "{p}", "--out", "{d}/m.ply"],
        ["export", "{p}", "pointcloud", "--out", "{d}/p.ply"],
        ["export", "{p}", "cameras", "--out", "{d}/c.json"],
        ["view", "{p}", "--exit-after", "1"],
    ],
    ids=lambda a: "-".join(x for x in a if not x.startswith("{")),
)
def test_a_missing_run_is_not_found(argv, tmp_path, capsys):
    missing = tmp_path / "no_such_run"
    argv = [a.format(p=missing, d=tmp_path) for a in argv]
    assert main(argv) == 2
    err = capsys.readouterr().err
    lines = [x for x in err.splitlines() if x.startswith("warpnerf ")]
    assert len(lines) == 1, err
    assert lines[0].startswith(f"warpnerf {argv[0]}: error: {missing}: not found"), lines[0]
    assert "not a training run" not in err and "Traceback" not in err
    assert sorted(p.name for p in tmp_path.iterdir()) == []  # nothing written
