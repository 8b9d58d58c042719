"""The README and the examples of docs/scripting.md and docs/testing-with-the-virtual-rig.md,
run as a reader would copy them: scripts with python, tests with plain pytest, shell
commands with bash, in a folder outside the repository.  Every command of the README
is checked against its program's own parser; the quick starts run for real on the
simulator."""

from __future__ import annotations

import os
import re
import shlex
import signal
import socket
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
DOCS = ROOT / "docs"
README = ROOT / "README.md"
QUICK_STARTS = ("Quick start: the lab operator", "Quick start: the test engineer", "Quick start: quality control")


def examples(page: str) -> list[str]:
    return re.findall(r"```python\n(.*?)```", (DOCS / page).read_text(), flags=re.S)


@pytest.mark.parametrize("number", range(len(examples("scripting.md"))))
def test_scripting_examples_run(tmp_path, number):
    script = tmp_path / "example.py"
    script.write_text(examples("scripting.md")[number])
    r = subprocess.run([sys.executable, str(script)], cwd=tmp_path, capture_output=True, text=True, timeout=600)
    assert r.returncode == 0, r.stdout[-3000:] + r.stderr[-3000:]


def test_testing_examples_pass_under_plain_pytest(tmp_path):
    for number, code in enumerate(examples("testing-with-the-virtual-rig.md")):
        (tmp_path / f"test_example_{number}.py").write_text(code)
    r = subprocess.run([sys.executable, "-m", "pytest", "-q", "-p", "no:cacheprovider"], cwd=tmp_path,
                       capture_output=True, text=True, timeout=600)
    assert r.returncode == 0 and f"{len(examples('testing-with-the-virtual-rig.md'))} passed" in r.stdout, \
        r.stdout[-4000:]


# ----- the README ------------------------------------------------------------------------------------
def sections(text: str | None = None) -> dict[str, str]:
    parts = re.split(r"^## (.+)$", README.read_text() if text is None else text, flags=re.M)
    return dict(zip(parts[1::2], parts[2::2], strict=True))


def blocks(text: str, language: str) -> list[str]:
    return re.findall(rf"```{language}\n(.*?)```", text, flags=re.S)


def commands(block: str) -> list[list[str]]:
    """The block's commands as a shell reads them: continuation lines joined, comments
    and a trailing ``&`` dropped."""
    joined = block.replace("\\\n", " ")
    return [args[:-1] if args[-1] == "&" else args
            for args in (shlex.split(line, comments=True) for line in joined.splitlines()) if args]


def test_the_readme_is_for_a_newcomer():
    text = README.read_text()
    assert len(text.splitlines()) <= 200
    found = sections()
    assert "Two commands" in found and {"make demo", "make test"} <= {
        " ".join(c[:2]) for b in blocks(found["Two commands"], "sh") for c in commands(b)}
    for title in QUICK_STARTS:
        (code,) = blocks(found[title], "sh") + blocks(found[title], "python")
        assert len(code.splitlines()) <= 10, title
    for link in re.findall(r"\]\((docs/[^)#]+)", text):
        assert (ROOT / link).is_file(), link


def every_readme_command() -> list[list[str]]:
    return [c for b in blocks(README.read_text(), "sh") for c in commands(b)]


@pytest.mark.parametrize("args", every_readme_command(), ids=lambda a: " ".join(a)[:60])
def test_every_readme_command_is_one_its_program_takes(args):
    """Options and values as the program's parser takes them (run for real below, where
    a test can: the quick starts)."""
    if args[0] == "make":
        r = subprocess.run(["make", "-n", *args[1:]], cwd=ROOT, capture_output=True, text=True)
        assert r.returncode == 0, r.stderr
        return
    if args[0] in ("ls", "kill", "sleep"):
        return
    assert args[:2] == ["python", "-m"], args
    package = __import__(f"{args[2]}.cli", fromlist=["build_parser"])
    package.build_parser().parse_args(args[3:])


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def on_free_ports(text: str, ports: tuple[str, ...]) -> str:
    """The README's fixed ports, free ones here (another test may hold them)."""
    for port in ports:
        text = text.replace(f"127.0.0.1:{port}", f"127.0.0.1:{free_port()}")
    return text


def simulator(serve: list[str], cwd: Path) -> subprocess.Popen:
    """The README's simulator line, started as the reader starts it; returns once it
    printed the options for rig (what the reader waits for)."""
    sim = subprocess.Popen([sys.executable, *serve[1:]], cwd=cwd, stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                           text=True, env=dict(os.environ, PYTHONPATH=str(ROOT)))
    assert sim.stdout is not None
    for line in sim.stdout:
        if line.startswith("rig options: "):
            return sim
    sim.wait()
    raise AssertionError(f"the simulator did not start: {sim.stderr.read() if sim.stderr else ''}")


def stop(sim: subprocess.Popen) -> None:
    sim.send_signal(signal.SIGTERM)
    sim.communicate(timeout=30)


def run_in_bash(lines: list[list[str]], cwd: Path) -> subprocess.CompletedProcess:
    script = "\n".join(shlex.join(c) if "*" not in " ".join(c) else " ".join(c) for c in lines)
    bin_dir = Path(sys.executable).parent
    return subprocess.run(["bash", "-c", f"set -x\n{script}"], cwd=cwd, capture_output=True, text=True,
                          timeout=1800, env=dict(os.environ, PATH=f"{bin_dir}:{os.environ['PATH']}",
                                                 PYTHONPATH=str(ROOT)))


@pytest.mark.slow
def test_the_operators_quick_start_runs(tmp_path):
    """On the simulator started as the README says; the console (a window) is only
    parsed, above."""
    found = sections(on_free_ports(README.read_text(), ("5020", "5021")))
    (serve,) = commands(blocks(found["Two commands"], "sh")[1])
    operator = [c for c in commands(blocks(found[QUICK_STARTS[0]], "sh")[0]) if c[3] != "gui"]
    sim = simulator(serve, tmp_path)
    try:
        r = run_in_bash(operator, tmp_path)
    finally:
        stop(sim)
    assert r.returncode == 0, r.stdout[-3000:] + r.stderr[-5000:]
    assert "state OFF" in r.stdout and "session complete" in r.stderr, r.stderr[-3000:]
    assert (tmp_path / "sessions" / "unit-17" / "RESULT.json").is_file()


@pytest.mark.slow
def test_the_test_engineers_quick_start_runs(tmp_path):
    (code,) = blocks(sections()[QUICK_STARTS[1]], "python")
    (tmp_path / "quick_start.py").write_text(code)
    r = subprocess.run([sys.executable, "quick_start.py"], cwd=tmp_path, capture_output=True, text=True, timeout=900)
    assert r.returncode == 0, r.stdout[-3000:] + r.stderr[-3000:]
    assert r.stdout.startswith("complete\n") and "theta6" in r.stdout, r.stdout


@pytest.mark.slow
def test_the_qc_quick_start_runs_as_pasted(tmp_path):
    """The worked example: the simulated unit with a worn orifice FAILs, is judged
    again, both records are in the history and both reports on disk."""
    (block,) = blocks(sections()[QUICK_STARTS[2]], "sh")
    lines = commands(on_free_ports(block, ("5030", "5031")))
    assert lines[0][1:4] == ["-m", "simulator", "serve"] and lines[1][0] == "sleep" and lines[-1][0] == "kill"
    sim = simulator(lines[0], tmp_path)       # the reader's sleep: here, until it says it is ready
    try:
        r = run_in_bash(lines[2:-1], tmp_path)
    finally:
        stop(sim)
    said = r.stdout + r.stderr
    assert "SN-0042: FAIL" in said and "+ python -m rig qc history" in said, said[-4000:]
    assert r.returncode == 0, said[-4000:]       # the last command, ls, found the reports
    history = said[said.index("+ python -m rig qc history"):]
    assert "SN-0042" in history, history
    assert len(list(tmp_path.glob("station/SN-0042-*/qc-report*.html"))) == 2   # the run's and the judgement's
