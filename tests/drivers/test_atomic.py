"""drivers.atomic: the one atomic writer (issue 20): whole files or none, no temporaries left, no clobbering."""
from __future__ import annotations

import stat

import pytest

from drivers.atomic import atomic_write, atomic_write_bytes


def test_a_failing_write_leaves_the_old_file_and_no_temporary(tmp_path):
    target = tmp_path / "frame.bin"
    atomic_write_bytes(target, b"old")

    def broken(tmp):
        tmp.write_bytes(b"half a fr")
        raise KeyboardInterrupt          # also an interrupt (Ctrl-C) mid-write

    with pytest.raises(KeyboardInterrupt):
        atomic_write(target, broken)
    assert target.read_bytes() == b"old"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["frame.bin"]


def test_no_clobber_mode_refuses_and_cleans_up(tmp_path):
    target = tmp_path / "sub" / "manifest.json"      # missing parents are made
    atomic_write_bytes(target, b"1", overwrite=False)
    with pytest.raises(FileExistsError, match="manifest.json: refusing to overwrite"):
        atomic_write_bytes(target, b"2", overwrite=False)

    def appears_meanwhile(tmp):                       # the target appears while the temporary is written
        tmp.write_bytes(b"3")
        target.with_name("late.json").write_bytes(b"other")

    with pytest.raises(FileExistsError):
        atomic_write(target.with_name("late.json"), appears_meanwhile, overwrite=False)
    assert target.with_name("late.json").read_bytes() == b"other" and target.read_bytes() == b"1"
    assert sorted(p.name for p in target.parent.iterdir()) == ["late.json", "manifest.json"]


def test_written_files_are_ordinary_data_files(tmp_path):
    p = atomic_write_bytes(tmp_path / "a.json", b"{}")
    assert stat.S_IMODE(p.stat().st_mode) == 0o644 and p.read_bytes() == b"{}"
