"""Atomic writes: complete files only, with the permissions a normal write would give."""

from __future__ import annotations

import os
import stat

import pytest

from kneegui.io.atomic import atomic_write_bytes, atomic_write_many


def test_new_file_gets_the_umask_mode_not_private(tmp_path):
    old = os.umask(0o022)
    try:
        path = atomic_write_bytes(tmp_path / "a.k", b"*KEYWORD\n")
    finally:
        os.umask(old)
    assert stat.S_IMODE(path.stat().st_mode) == 0o644


def test_replacing_a_file_keeps_its_mode(tmp_path):
    path = tmp_path / "b.k"
    path.write_bytes(b"old")
    path.chmod(0o640)
    atomic_write_bytes(path, b"new")
    assert path.read_bytes() == b"new"
    assert stat.S_IMODE(path.stat().st_mode) == 0o640


def test_group_write_replaces_nothing_if_one_file_fails(tmp_path):
    keep = tmp_path / "keep.k"
    keep.write_bytes(b"previous")
    blocked = tmp_path / "dir_in_the_way"
    blocked.mkdir()
    with pytest.raises(OSError):
        atomic_write_many({keep: b"new", blocked: b"cannot replace a folder"})
    assert keep.read_bytes() == b"previous"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["dir_in_the_way", "keep.k"]
