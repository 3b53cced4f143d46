"""The command line: help with examples, one-line errors, no tracebacks for user errors."""

from __future__ import annotations

import subprocess
import sys

import pytest

from unipixie import cli


def _run(*args):
    return subprocess.run([sys.executable, "-m", "unipixie.cli", *args], capture_output=True, text=True)


def test_help_lists_commands():
    res = _run("--help")
    assert res.returncode == 0
    for name in ("doctor", "build-extension"):
        assert name in res.stdout


def test_every_command_has_help_with_examples(capsys):
    parser = cli.build_parser()
    sub = next(a for a in parser._actions if a.dest == "command")
    assert sub.choices, "no subcommands registered"
    for name, p in sub.choices.items():
        text = p.format_help()
        assert "examples:" in text, f"'unipixie {name} --help' shows no examples"
        assert f"unipixie {name.split()[0]}" in text


def test_unknown_command_is_one_line_error():
    res = _run("no-such-command")
    assert res.returncode == 2
    assert "Traceback" not in res.stderr
    assert len(res.stderr.strip().splitlines()) == 1


def test_bad_option_is_one_line_error():
    res = _run("doctor", "--no-such-option")
    assert res.returncode == 2
    assert "Traceback" not in res.stderr
    assert len(res.stderr.strip().splitlines()) == 1


def test_user_error_is_reported_without_traceback(monkeypatch, capsys):
    from unipixie.core.errors import UserError
    from unipixie.core.commands import doctor

    def boom(args):
        raise UserError("the thing is missing; put it in /x")

    monkeypatch.setattr(doctor, "run", boom)
    status = cli.main(["doctor"])
    err = capsys.readouterr().err
    assert status == 2
    assert err.strip() == "unipixie doctor: error: the thing is missing; put it in /x"


def test_arguments_after_double_dash_are_used(monkeypatch):
    monkeypatch.setattr(sys, "argv", ["blender", "-b", "--python-expr", "x", "--", "--version"])
    with pytest.raises(SystemExit) as exc:
        cli.main()
    assert exc.value.code == 0


def test_console_script_exists():
    import shutil
    import os

    exe = shutil.which("unipixie", path=os.path.dirname(sys.executable))
    assert exe, "the 'unipixie' console script is not installed next to the interpreter"
    res = subprocess.run([exe, "--help"], capture_output=True, text=True)
    assert res.returncode == 0 and "doctor" in res.stdout
