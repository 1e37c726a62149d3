"""The house's import contracts (pyproject.toml, [tool.importlinter]) hold over the whole tree: the layers,
what the service runs never importing the offline wing or torch, and no import circle anywhere. Imports
inside functions count too. docs/architecture.md draws the same layers."""

import os
import re
import shutil
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def lint_imports() -> str:
    """Where the lint-imports command is: beside this Python (a virtual environment), else on the PATH."""
    beside = Path(sys.executable).parent / "lint-imports"
    found = str(beside) if beside.is_file() else shutil.which("lint-imports")
    assert found, "lint-imports is missing: pip install 'hapticlink[dev]' (import-linter)"
    return found


def test_every_import_contract_is_kept():
    run = subprocess.run(
        [lint_imports(), "--no-cache"],
        cwd=ROOT,
        capture_output=True,
        text=True,
        env={**os.environ, "PYTHONPATH": str(ROOT)},  # our packages from this checkout
        timeout=240,
    )
    verdicts = dict(re.findall(r"^(.+?) (KEPT|BROKEN)$", run.stdout, re.M))
    assert verdicts, f"lint-imports reported no contract (exit {run.returncode}):\n{run.stdout}\n{run.stderr}"
    broken = [name for name, verdict in verdicts.items() if verdict == "BROKEN"]
    assert not broken, f"broken import contracts: {broken}\n{run.stdout[run.stdout.find('Broken contracts') :]}"
    assert run.returncode == 0, run.stdout + run.stderr
    declared = re.findall(r"^\[\[tool\.importlinter\.contracts\]\]$", (ROOT / "pyproject.toml").read_text(), re.M)
    assert len(verdicts) == len(declared), f"checked {sorted(verdicts)}, pyproject declares {len(declared)}"
