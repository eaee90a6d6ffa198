"""The commit word (:mod:`capevo.storage.commit_word`): every committed write of any process
moves it before returning; reads and refused writes leave it; a bad location is Unavailable."""

from __future__ import annotations

import multiprocessing as mp
from pathlib import Path

import pytest

from capevo.errors import Conflict, Unavailable
from capevo.registry.descriptor import parse_publish_spec
from capevo.registry.local import DB_FILENAME, LocalRegistry
from capevo.storage.commit_word import SUFFIX, WORD_BYTES, CommitWord

SPEC = parse_publish_spec("kind: code\ndescription: commit word probe\n")


def _publish_and_promote(root: str) -> None:
    with LocalRegistry(root, actor="other-process") as reg:
        reg.publish("elsewhere", b"x", SPEC)
        reg.promote("elsewhere", 0)


def test_every_committed_write_moves_the_word_and_nothing_else_does(tmp_path: Path) -> None:
    with LocalRegistry(tmp_path / "reg") as reg:
        word = CommitWord(tmp_path / "reg" / DB_FILENAME)  # a second mapping, as another process has
        try:
            seen = {word.load()}
            for write in (
                lambda: reg.publish("alpha", b"a0", SPEC),
                lambda: reg.publish("alpha", b"a1", SPEC),
                lambda: reg.promote("alpha", 0),
                lambda: reg.promote("alpha", 1, expected_active=0),
                lambda: reg.rollback("alpha"),
            ):
                write()
                now = word.load()
                assert now not in seen, "a committed write left the word where it was"
                seen.add(now)
            before = word.load()
            reg.get_version("alpha")
            reg.list_ecms()
            reg.history()
            with pytest.raises(Conflict):
                reg.promote("alpha", 1, expected_active=1)  # refused and rolled back: nothing committed
            assert word.load() == before
        finally:
            word.close()


def test_a_commit_in_another_process_moves_this_process_word(tmp_path: Path) -> None:
    root = tmp_path / "reg"
    with LocalRegistry(root) as reg:
        reg.publish("here", b"h", SPEC)
        word = CommitWord(root / DB_FILENAME)
        try:
            before = word.load()
            child = mp.get_context("spawn").Process(target=_publish_and_promote, args=(str(root),))
            child.start()
            child.join(120)
            assert child.exitcode == 0
            assert word.load() != before
            assert reg.get_version("elsewhere").version == 0
        finally:
            word.close()


def test_the_word_file_is_one_word_and_opening_it_again_keeps_it(tmp_path: Path) -> None:
    db = tmp_path / "x.sqlite3"
    first = CommitWord(db)
    first.move()
    second = CommitWord(db)  # a later opener neither truncates nor rewrites it
    try:
        assert Path(f"{db}{SUFFIX}").stat().st_size == WORD_BYTES
        assert second.load() == first.load()
        second.move()
        assert first.load() == second.load()
    finally:
        first.close()
        second.close()
    second.close()  # idempotent
    with pytest.raises(Unavailable, match="closed"):
        first.load()
    with pytest.raises(Unavailable, match="closed"):
        first.move()


def test_a_word_that_cannot_be_made_is_unavailable(tmp_path: Path) -> None:
    db = tmp_path / "x.sqlite3"
    Path(f"{db}{SUFFIX}").mkdir()  # something else holds the word's name
    with pytest.raises(Unavailable, match="cannot open"):
        CommitWord(db)
    root = tmp_path / "reg"
    root.mkdir()
    Path(f"{root / DB_FILENAME}{SUFFIX}").mkdir()
    with pytest.raises(Unavailable, match="cannot open"):
        LocalRegistry(root)  # the store refuses to open without its word
