"""Files are replaced whole or not at all."""

from __future__ import annotations

import os
import stat

import pytest

from tpsr_ros.io.atomic import atomic_file


def test_the_file_is_replaced_only_when_the_block_ends_well(tmp_path):
    target = tmp_path / "model.npz"
    target.write_bytes(b"old")
    with atomic_file(target) as handle:
        handle.write(b"new")
        assert target.read_bytes() == b"old"  # nothing visible before the rename
    assert target.read_bytes() == b"new"
    with pytest.raises(RuntimeError), atomic_file(target, "w") as text:
        text.write("half")
        raise RuntimeError("disk full")
    assert target.read_bytes() == b"new"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["model.npz"]  # no temporary left


def test_a_link_at_the_target_is_replaced_not_followed(tmp_path):
    elsewhere = tmp_path / "elsewhere"
    elsewhere.mkdir()
    kept = elsewhere / "kept.xml"
    kept.write_text("theirs")
    link = tmp_path / "profile.xml"
    link.symlink_to(kept)
    with atomic_file(link, "w", sync=False) as handle:
        handle.write("ours")
    assert not link.is_symlink() and link.read_text() == "ours"
    assert kept.read_text() == "theirs" and list(elsewhere.iterdir()) == [kept]


def test_the_new_file_gets_the_permissions_a_plain_open_would_give(tmp_path):
    fresh = tmp_path / "model.npz"
    old_mask = os.umask(0o027)
    try:
        with atomic_file(fresh) as handle:
            handle.write(b"x")
        assert stat.S_IMODE(fresh.stat().st_mode) == 0o640  # not mkstemp's 0o600
    finally:
        os.umask(old_mask)
    shared = tmp_path / "metadata.yaml"
    shared.write_text("old")
    shared.chmod(0o664)
    with atomic_file(shared, "w") as text:
        text.write("new")
    assert stat.S_IMODE(shared.stat().st_mode) == 0o664  # the replaced file's kept


def test_given_permissions_replace_those_of_the_old_file(tmp_path):
    planted = tmp_path / "profile.xml"
    planted.write_text("theirs")
    planted.chmod(0o666)  # writable by anyone: its mode must not carry over
    with atomic_file(planted, "w", sync=False, permissions=0o644) as handle:
        handle.write("ours")
    assert stat.S_IMODE(planted.stat().st_mode) == 0o644 and planted.read_text() == "ours"
