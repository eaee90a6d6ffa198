"""trace_files: which trace files a list of paths names, for blame (strict, recursive) and for
the learners (lenient, one level)."""

from __future__ import annotations

from pathlib import Path

import pytest

from capevo.errors import NotFound
from capevo.runtime.traces.files import trace_files


def _touch(path: Path) -> Path:
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_bytes(b"")
    return path


def test_directories_give_their_traces_in_name_order_and_files_are_taken_as_given(tmp_path: Path) -> None:
    b = _touch(tmp_path / "run" / "b.mcap")
    a = _touch(tmp_path / "run" / "a.mcap")
    _touch(tmp_path / "run" / "notes.txt")
    deep = _touch(tmp_path / "run" / "eval-1" / "c.mcap")
    odd = _touch(tmp_path / "elsewhere" / "kept.bin")
    assert trace_files([tmp_path / "run", odd]) == [a.resolve(), b.resolve(), odd.resolve()]
    assert trace_files([str(tmp_path / "run")], recursive=True) == [a.resolve(), b.resolve(), deep.resolve()]


def test_each_file_comes_once_in_first_seen_order(tmp_path: Path) -> None:
    a = _touch(tmp_path / "a.mcap")
    b = _touch(tmp_path / "b.mcap")
    assert trace_files([b, tmp_path, tmp_path / "." / "a.mcap"]) == [b.resolve(), a.resolve()]


def test_a_missing_path_or_an_empty_directory_is_not_found_unless_missing_is_ok(tmp_path: Path) -> None:
    empty = tmp_path / "empty"
    empty.mkdir()
    with pytest.raises(NotFound, match="no such trace"):
        trace_files([tmp_path / "gone.mcap"])
    with pytest.raises(NotFound, match=r"no \*\.mcap file under"):
        trace_files([empty])
    kept = _touch(tmp_path / "x.mcap")
    assert trace_files([tmp_path / "gone.mcap", empty, kept], missing_ok=True) == [kept.resolve()]
    assert trace_files([], missing_ok=True) == []
