"""Every help screen: ``-h`` as ``--help``, flags shown as flags, one short meaning per
short option, and a working example at the end, of which the cheap ones are run."""

from __future__ import annotations

import shlex
from pathlib import Path

import pytest
import typer.main
from typer.testing import CliRunner

from fringecal.flows.cli import app
from fringecal.flows.help import EXAMPLE

ROOT = Path(__file__).resolve().parents[1]
runner = CliRunner()


def _commands(command=None, path=()):
    """(path, command) of the app, every group and every command, depth first."""
    command = command or typer.main.get_command(app)
    yield path, command
    for name, sub in getattr(command, "commands", {}).items():
        yield from _commands(sub, (*path, name))


COMMANDS = dict(_commands())
PATHS = list(COMMANDS)


def _example(help_text: str) -> str:
    """The example at the end of a help screen (joined again where rich wrapped it)."""
    head, sep, tail = help_text.rpartition(EXAMPLE)
    assert sep, f"no {EXAMPLE!r} in:\n{help_text}"
    return " ".join(tail.split())


@pytest.mark.parametrize("path", PATHS, ids=[" ".join(p) or "fringecal" for p in PATHS])
def test_every_help_ends_with_an_example_of_its_command(path):
    res = runner.invoke(app, [*path, "--help"])
    assert res.exit_code == 0, res.output
    example = _example(res.output)  # all that follows the last "Example: "
    name = " ".join(["fringecal", *path])
    assert example == name or example.startswith(name + " "), example
    assert example == " ".join(COMMANDS[path].epilog.removeprefix(EXAMPLE).split())
    assert runner.invoke(app, [*path, "-h"]).output == res.output  # -h is --help, everywhere
    assert "<bool>" not in res.output  # flags take no value


def test_version():
    from fringecal import __version__

    res = runner.invoke(app, ["--version"])
    assert res.exit_code == 0 and res.output == f"fringecal {__version__}\n"


def test_each_short_option_has_one_meaning():
    """-c is a config, -r a run directory, -h help: in every command that has them."""
    meaning = {"-c": {"--config"}, "-r": {"--run"}, "-h": {"--help"}}
    for path, command in COMMANDS.items():
        for param in command.params:
            names = set(getattr(param, "opts", [])) | set(getattr(param, "secondary_opts", []))
            for short, longs in meaning.items():
                if short in names:
                    assert longs & names, f"fringecal {' '.join(path)}: {short} is {sorted(names)}"


def test_commands_that_read_a_run_take_run_r():
    for path in [("step",), ("calibrate",), ("report",), ("reproduce",), ("measure",), ("verify", "plan"),
                 ("verify", "acceptance"), ("verify", "ballbar"), ("export", "opencv"), ("run",)]:
        names = {o for p in COMMANDS[path].params for o in getattr(p, "opts", [])}
        assert {"--run", "-r"} <= names, path


# -- the cheap examples, run as printed, from a folder where configs/ is the checkout's --

CHEAP = [
    [("pose",)],
    [("verify", "ballbar")],
    [("fit", "sphere")], [("fit", "plane")],
    [("hexapod", "ik")], [("hexapod", "fk")], [("hexapod", "workspace")], [("hexapod", "drift")],
    [("hexapod", "move")], [("hexapod", "plan"), ("hexapod", "run-file")],
    [("artefact", "truss")], [("artefact", "rigidity")], [("artefact", "sag")], [("artefact", "cte")],
    [("artefact", "thermal")], [("artefact", "cme")], [("artefact", "consistency")],
    [("export", "opencv"), ("import", "opencv")],
]


@pytest.mark.parametrize("chain", CHEAP, ids=[" + ".join(" ".join(p) for p in c) for c in CHEAP])
def test_cheap_examples_work(chain, tmp_path, monkeypatch):
    (tmp_path / "configs").symlink_to(ROOT / "configs")
    monkeypatch.chdir(tmp_path)
    for path in chain:
        args = shlex.split(COMMANDS[path].epilog.removeprefix(EXAMPLE))
        assert args[:1 + len(path)] == ["fringecal", *path]
        res = runner.invoke(app, args[1:])
        assert res.exit_code == 0, f"{' '.join(args)}:\n{res.output}"
