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


def _cancel_at(call: int):
    """A cancel callback that answers True from its ``call``-th question on; it counts them."""
    asked = [0]

    def cancel() -> bool:
        asked[0] += 1
        return asked[0] >= call

    return cancel, asked


@pytest.mark.parametrize("call", [1, 2, 3, 5])
def test_a_cancelled_group_write_replaces_nothing_and_leaves_no_temp_file(
    tmp_path, monkeypatch, call
):
    """Asked between chunks and before the renames: a cancel at any of them leaves the old files
    and no ``.part`` file (two files of 2 and 1 chunks: 4 questions in all)."""
    from kneegui.errors import Cancelled
    from kneegui.io import atomic

    monkeypatch.setattr(atomic, "WRITE_CHUNK", 4)
    first, second = tmp_path / "main.k", tmp_path / "part.k"
    first.write_bytes(b"old main")
    cancel, asked = _cancel_at(call)
    if call > 4:
        atomic_write_many({first: b"12345678", second: b"abc"}, cancel)
        assert asked[0] == 4 and first.read_bytes() == b"12345678"
        assert second.read_bytes() == b"abc"
        return
    with pytest.raises(Cancelled, match="nothing written"):
        atomic_write_many({first: b"12345678", second: b"abc"}, cancel)
    assert asked[0] == call
    assert first.read_bytes() == b"old main"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["main.k"]
