"""The `xyzcyl` console script (cli.py; its parser common/command.py), issue 27: negative numbers in scientific
notation for every command (defect 2), the extra to install when a command's dependency is missing (defect 3),
--version, and help that covers every flag and names only flags that exist (defect 7); issue 36: `xyzcyl export` is
the export of scenes (issue 39: USDZ), the model's export `xyzcyl export-model` (the old spelling still runs it,
with a notice)."""

from __future__ import annotations

import argparse
import json
import re
import subprocess
import sys
from importlib.metadata import version

import pytest
from xyzcyl import cli


def _all_parsers() -> dict[str, argparse.ArgumentParser]:
    """Every parser of xyzcyl by its command line ("" the top level, "client render", "data synth", ...)."""
    found = {}

    def walk(p, name):
        found[name] = p
        for a in p._actions:
            if isinstance(a, argparse._SubParsersAction):
                for sub, sp in a.choices.items():
                    walk(sp, f"{name} {sub}".strip())

    walk(cli.build_parser()[0], "")
    for cmd in cli.COMMANDS:
        walk(cli.command_parser(cmd)[0], cmd.name)
    return found


# -- negative numbers ----------------------------------------------------------------------------------------

def test_negative_numbers_in_any_notation_are_values():
    p = cli.Parser(prog="t")
    p.add_argument("pos", type=float)
    p.add_argument("--pair", type=float, nargs=2)
    p.add_argument("--one", type=float)
    args = p.parse_args(["-2e0", "--pair", "-1e-05", "-1.5E+3", "--one", "-.5e1"])
    assert (args.pos, args.pair, args.one) == (-2.0, [-1e-05, -1500.0], -5.0)
    assert p.parse_args(["1", "--pair=-1e-05", "-3", "--one=-4e-1"]).pair == [-1e-05, -3.0]   # "=" with 2 values
    with pytest.raises(SystemExit):
        p.parse_args(["1", "--pair", "-x", "2"])                                  # an option is still an option


def test_every_xyzcyl_parser_takes_them():
    """The sub-parsers (client render, data synth) inherit the class, so the fix holds for every command."""
    parsers = _all_parsers()
    assert all(isinstance(p, cli.Parser) for p in parsers.values()), \
        [n for n, p in parsers.items() if not isinstance(p, cli.Parser)]
    args = parsers["client render"].parse_args(["SID", "--carla", "5", "-1e-05", "1.6", "-2e0", "0", "0",
                                                "--fov", "90", "--out", "x.png", "--forward", "-2e0"])
    assert args.carla == [5.0, -1e-05, 1.6, -2.0, 0.0, 0.0] and args.forward == -2.0
    pose = "0 0 1 5 -1 0 0 -1e-05 0 -1 0 1.6 0 0 0 1"
    args = parsers["render"].parse_args(["S", "--K", "5.7e2", "571.3", "399.5", "224.5", "--cam-to-world",
                                         *pose.split(" "), "--out", "x.png"])
    assert args.cam_to_world == [pose]          # the 16 numbers as one value, read by pose_flags.parse_matrix


# -- --version -------------------------------------------------------------------------------------------------

def test_version(capsys):
    with pytest.raises(SystemExit) as e:
        cli.main(["--version"])
    assert e.value.code == 0
    out = capsys.readouterr().out.splitlines()
    assert out[0] == f"xyzcyl {version('xyzcyl')}" and out[1].startswith("model: ")   # issue 35: the model's too


# -- help ------------------------------------------------------------------------------------------------------

def test_every_argument_of_every_command_has_help():
    missing = [f"xyzcyl {name}: {a.option_strings or a.dest}" for name, p in _all_parsers().items()
               for a in p._actions
               if not isinstance(a, (argparse._HelpAction, argparse._SubParsersAction))
               and (not a.help or a.help == argparse.SUPPRESS)]
    assert missing == []


FLAG = r"(?<![\w-])--[a-z][a-z0-9-]*"


def test_help_names_only_flags_that_exist():
    """A flag named in a command's help is one of its own options, or, inside `xyzcyl OTHER ...`, one of OTHER's
    (lidar-eval's help named a --lidar flag that it does not have)."""
    parsers = _all_parsers()

    def options(p):
        return {o for a in p._actions for o in a.option_strings}

    wrong = []
    for name, p in parsers.items():
        for text in [p.description or ""] + [a.help or "" for a in p._actions]:
            for quoted in re.findall(r"`([^`]*)`", text):
                if quoted.startswith("xyzcyl "):
                    words = quoted.split()[1:]
                    other = next((" ".join(words[:k]) for k in range(len(words), 0, -1)
                                  if " ".join(words[:k]) in parsers), None)
                    wrong += [f"{name}: `{quoted}`" for f in re.findall(FLAG, quoted)
                              if other is None or f not in options(parsers[other])]
            wrong += [f"{name}: {f}" for f in re.findall(FLAG, re.sub(r"`[^`]*`", "", text))
                      if f not in options(p)]
    assert wrong == []


def test_train_help_names_every_stage(capsys):
    with pytest.raises(SystemExit):
        cli.main(["train", "--help"])
    out = capsys.readouterr().out
    stages = next(a.choices for a in _all_parsers()["train"]._actions if a.dest == "stage")
    description = out.split("\n\n")[1]
    assert all(s in description for s in stages), description


# -- export: scenes, export-model: the model ---------------------------------------------------------------------

def test_export_is_the_export_of_scenes(capsys):
    """`xyzcyl export` exports a scene folder (tests/runtime/test_usdz.py: what it writes); without its arguments it
    says which (argparse: exit 2), and its help names the model's export command."""
    with pytest.raises(SystemExit) as e:
        cli.main(["export"])
    assert e.value.code == 2 and "SCENE_DIR" in capsys.readouterr().err
    with pytest.raises(SystemExit) as e:
        cli.main(["export", "scene", "--format", "usdz"])                 # no --out
    assert e.value.code == 2 and "--out" in capsys.readouterr().err
    from xyzcyl.runtime.commands import export

    assert "`xyzcyl export-model`" in export.__doc__


def test_old_export_spelling_runs_export_model_with_a_notice(tmp_path, capsys):
    pytest.importorskip("torch")
    assert cli.main(["export", "--checkpoint", str(tmp_path / "none.pt"), "--out", str(tmp_path / "m")]) == 2
    err = capsys.readouterr().err.splitlines()
    assert err[0] == cli.OLD_EXPORT_NOTICE == ("xyzcyl export --checkpoint is now `xyzcyl export-model`; "
                                               "the old spelling goes in the next release")
    assert err[1].startswith("xyzcyl export-model: checkpoint: ") and len(err) == 2
    assert not (tmp_path / "m").exists()


# -- missing optional dependencies -----------------------------------------------------------------------------

SCRIPT = """
import contextlib, io, json, sys
for m in sys.argv[1].split(","):
    sys.modules[m] = None                     # as if not installed: import raises ModuleNotFoundError
from xyzcyl import cli
out = []
for argv in json.loads(sys.argv[2]):
    err = io.StringIO()
    with contextlib.redirect_stderr(err):
        rc = cli.main(argv)
    out.append([rc, err.getvalue()])
print(json.dumps(out))
"""


def _without(modules: str, commands: list[list[str]]) -> list[tuple[int, str]]:
    r = subprocess.run([sys.executable, "-c", SCRIPT, modules, json.dumps(commands)], capture_output=True,
                       text=True, timeout=300, check=False)
    assert r.returncode == 0, r.stderr[-3000:]
    return json.loads(r.stdout.strip().splitlines()[-1])


def test_torch_commands_without_torch_name_the_extra(tmp_path):
    """The serving install has no torch: train, eval, export and import-model say which extra to install, in one
    line with exit status 2, instead of a ModuleNotFoundError traceback."""
    data = tmp_path / "data"
    data.mkdir()
    commands = [["train", "--data", str(data), "--stage", "occ", "--out", str(tmp_path / "run")],
                ["eval", "--data", str(data), "--setting", "ego-forward"],
                ["export-model", "--checkpoint", str(tmp_path / "c.pt"), "--out", str(tmp_path / "model")],
                ["import-model", str(cli.__file__), "--out", str(tmp_path / "c.pt")],
                ["export", f"--checkpoint={tmp_path / 'c.pt'}", "--out", str(tmp_path / "model")]]   # old spelling
    results = _without("torch", commands)
    for argv, (rc, err) in zip(commands[:-1], results):
        assert (rc, err) == (2, f"xyzcyl {argv[0]}: missing dependency 'torch' (pip install 'xyzcyl[train]')\n")
    # `xyzcyl export --checkpoint` runs export-model, after one line saying so
    assert results[-1] == [2, f"{cli.OLD_EXPORT_NOTICE}\n"
                              "xyzcyl export-model: missing dependency 'torch' (pip install 'xyzcyl[train]')\n"]


def test_server_and_client_without_their_extras_name_them(tmp_path):
    commands = [["serve", "--print-settings"], ["client", "scenes"]]
    (serve_rc, serve_err), (client_rc, client_err) = _without("pydantic_settings,httpx", commands)
    assert (serve_rc, client_rc) == (2, 2)
    assert serve_err == "xyzcyl serve: missing dependency 'pydantic_settings' (pip install 'xyzcyl[server]')\n"
    assert client_err == "xyzcyl client: missing dependency 'httpx' (pip install 'xyzcyl[client]')\n"
