"""The examples of docs/scripting.md and docs/testing-with-the-virtual-rig.md, run as
a reader would copy them: scripts with python, tests with plain pytest, in a folder
outside the repository."""

from __future__ import annotations

import re
import subprocess
import sys
from pathlib import Path

import pytest

DOCS = Path(__file__).resolve().parents[1] / "docs"


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
