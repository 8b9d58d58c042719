"""A usage error on any of the three command lines is one line that says what is wrong
and where the usage is, with exit status 2 (argparse's own answer is the whole usage first)."""

from __future__ import annotations

import pytest

from identify.cli import build_parser as identify_parser
from rig.cli import build_parser as rig_parser
from rig.gui.options import ConsoleOptions
from simulator.cli import build_parser as simulator_parser


@pytest.mark.parametrize(("parser", "argv", "says"), [
    (rig_parser, ["run", "--order", "nope"],
     "python -m rig run: error: argument --order: invalid choice: 'nope' (choose from 'thermal', 'fixed') "
     "(see python -m rig run --help)"),
    (rig_parser, [], "python -m rig: error: the following arguments are required: command"),
    (simulator_parser, ["serve", "--physics", "plnat"],
     "python -m simulator serve: error: argument --physics: invalid choice: 'plnat'"),
    (identify_parser, ["fit"], "python -m identify fit: error: the following arguments are required: dataset"),
])
def test_a_usage_error_is_one_line_with_exit_2(parser, argv, says, capsys):
    with pytest.raises(SystemExit) as ended:
        parser().parse_args(argv)
    assert ended.value.code == 2
    (line,) = capsys.readouterr().err.splitlines()
    assert line.startswith(says) and line.endswith("--help)"), line


def test_the_consoles_options_too(capsys):
    with pytest.raises(SystemExit) as ended:
        ConsoleOptions.parse(["gui", "--speed", "x"])
    assert ended.value.code == 2
    (line,) = capsys.readouterr().err.splitlines()
    assert line == "python -m rig gui: error: argument --speed: invalid float value: 'x' (see python -m rig gui --help)"
