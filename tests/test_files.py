"""Files written whole or not at all, with the permissions of any new file."""

import os
import stat
from pathlib import Path

import pytest

from fastsdf.files import atomic_write


def _mode(path):
    return stat.S_IMODE(os.stat(path).st_mode)


def test_written_file_has_the_permissions_of_a_new_file(tmp_path):
    old = os.umask(0o022)
    try:
        target = tmp_path / "out.txt"
        atomic_write(target, lambda tmp: Path(tmp).write_text("data"))
        assert target.read_text() == "data"
        assert _mode(target) == 0o644  # not mkstemp's 0o600
        assert os.listdir(tmp_path) == ["out.txt"]
    finally:
        os.umask(old)


def test_failed_write_leaves_the_old_file_and_no_temporary(tmp_path):
    target = tmp_path / "out.txt"
    target.write_text("old")

    def fail(tmp):
        with open(tmp, "w") as fh:
            fh.write("half")
        raise OSError("disk full")

    with pytest.raises(OSError, match="disk full"):
        atomic_write(target, fail)
    assert target.read_text() == "old" and os.listdir(tmp_path) == ["out.txt"]
