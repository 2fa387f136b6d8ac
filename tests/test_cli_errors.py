"""Bad input on the command line: one line naming the problem and a non-zero exit, the traceback only with --debug."""

import os
import subprocess
import sys

import pytest

from pivla.cli import main
from pivla.cli.app import DEBUG_ENV
from pivla.data.episode import DatasetError


def test_a_user_error_is_one_line_and_debug_shows_the_exception(tmp_path, monkeypatch):
    monkeypatch.delenv(DEBUG_ENV, raising=False)
    with pytest.raises(SystemExit) as info:
        main(["train", "--data", str(tmp_path), "--out", str(tmp_path / "run"), "--steps", "2"])
    first, hint = str(info.value.code).splitlines()
    assert first == f"pivla train: DatasetError: {tmp_path}: no .hdf5 files found"
    assert "--debug" in hint
    with pytest.raises(DatasetError, match="no .hdf5 files"):
        main(["train", "--data", str(tmp_path), "--out", str(tmp_path / "run"), "--steps", "2", "--debug"])
    assert DEBUG_ENV not in os.environ  # --debug holds for its own command only
    assert not (tmp_path / "run" / "model.safetensors").exists()


def test_the_process_exits_non_zero_without_a_traceback(tmp_path):
    missing = tmp_path / "nothing-here"
    proc = subprocess.run([sys.executable, "-m", "pivla", "report", "--dir", str(missing)], capture_output=True,
                          text=True, env={"PATH": "/usr/bin:/bin"}, timeout=120)
    assert proc.returncode != 0
    assert "Traceback" not in proc.stderr and str(missing) in proc.stderr, proc.stderr
