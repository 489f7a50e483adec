"""fitter.process_exit: a command's process ends after Python's exit handlers, with its code."""

from __future__ import annotations

import subprocess
import sys

SCRIPT = """
import atexit, sys
from fitter.process_exit import exit_now
atexit.register(lambda: open(sys.argv[1], "w").write("ran"))
print("written before the exit", end="")
exit_now(int(sys.argv[2]))
"""


def test_exit_now_runs_the_exit_handlers_flushes_and_ends_with_the_code(tmp_path):
    for code in (0, 3):
        flag = tmp_path / f"flag{code}"
        done = subprocess.run([sys.executable, "-c", SCRIPT, str(flag), str(code)],
                              capture_output=True, text=True, timeout=60)
        assert done.returncode == code
        assert done.stdout == "written before the exit"  # flushed: stdout is a pipe here
        assert flag.read_text() == "ran"


def test_the_tessera_command_ends_through_exit_now():
    import tomllib
    from pathlib import Path

    project = tomllib.loads((Path(__file__).parents[1] / "pyproject.toml").read_text())
    assert project["project"]["scripts"]["tessera"] == "fitter.cli:console"
