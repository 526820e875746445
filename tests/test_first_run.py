"""The first run on a fresh machine: what the real Makefile would do (a dry run that
rebuilds everything), and what `prox setup` tells the user meanwhile."""
from __future__ import annotations

import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).parents[1]


def _dry_run(target: str) -> str:
    return subprocess.run(["make", "-n", "-B", target], cwd=ROOT, capture_output=True,
                          text=True, check=True).stdout


def test_make_installs_the_cpu_torch_and_only_what_each_command_needs():
    demo = _dry_run("demo")
    assert "--index-url https://download.pytorch.org/whl/cpu" in demo
    assert "torch==2.13.0" in demo and "torch.version.cuda is None" in demo
    assert "redis-server libosmesa6" in demo
    assert "chromium" not in demo and "tidy" not in demo  # only the report tests use them
    assert "chromium tidy" in _dry_run("test")


def test_prox_setup_says_what_it_does_and_nothing_of_warp():
    run = subprocess.run([sys.executable, "-m", "prox_engine.cli", "setup"], cwd=ROOT,
                         capture_output=True, text=True, check=True, timeout=900)
    assert "compiling the warp kernels: skinning, bone chain, keypoints" in run.stdout
    assert "anny model data:" in run.stdout
    assert "Warp" not in run.stdout + run.stderr
