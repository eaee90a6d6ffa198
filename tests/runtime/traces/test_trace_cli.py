"""``capevo trace`` commands (capevo.cli.trace invariants 1-3), through click's runner and ``python -m``."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from _trace_helpers import make_env_step, make_metadata, one_of_each, write_records, write_trace
from click.testing import CliRunner, Result

from capevo.cli.trace import trace
from capevo.runtime.traces import EnvStep, TraceReader, TraceWriter, Transitions


def run(*args: str) -> Result:
    return CliRunner().invoke(trace, list(args), catch_exceptions=False)


@pytest.fixture
def two_episodes(tmp_path: Path) -> Path:
    records = one_of_each(0) + [make_env_step(1, i, obs_dim=50) for i in range(3)] + one_of_each(1)[-1:]
    return write_trace(tmp_path / "run.mcap", records)


@pytest.fixture
def unfinished(tmp_path: Path) -> Path:
    """A trace whose writer vanished: copied bytes of an open, flushed file."""
    path = tmp_path / "live.mcap"
    with TraceWriter(path, make_metadata(), background_flush=False) as w:
        write_records(w, [*one_of_each(0)[:-1], make_env_step(1, 0)])
        w.flush()
        crashed = tmp_path / "crashed.mcap"
        crashed.write_bytes(path.read_bytes())
    return crashed


def test_summary_table(two_episodes: Path) -> None:
    result = run("summary", str(two_episodes))
    assert result.exit_code == 0, result.output
    out = result.output
    assert "run run-1  task Lift  registry revision 4  file complete" in out
    assert "EPISODE" in out and "INTERVENTIONS" in out
    assert "2 episodes (2 finished), success rate 100.0%, 4 interventions" in out


def test_summary_json(two_episodes: Path) -> None:
    # Invariant 2: exactly one JSON document.
    result = run("summary", str(two_episodes), "--json")
    assert result.exit_code == 0
    doc = json.loads(result.output)
    assert doc["run_id"] == "run-1" and doc["complete"] is True
    assert [e["episode"] for e in doc["episodes"]] == [0, 1]
    assert doc["episodes"][0]["success"] is True and doc["episodes"][0]["interventions"] == 2


def test_summary_of_a_crashed_file_says_so(unfinished: Path) -> None:
    result = run("summary", str(unfinished))
    assert result.exit_code == 0, result.output
    assert "UNFINISHED (run `capevo trace recover` to salvage it)" in result.output
    assert "2 episodes (0 finished)" in result.output


def test_export_npz_default(two_episodes: Path) -> None:
    result = run("export", str(two_episodes), "--episodes")  # bare flag: all episodes
    assert result.exit_code == 0, result.output
    out = two_episodes.with_name("run.transitions.npz")
    assert f"wrote 4 transitions from 2 episodes to {out} (npz; obs dim 50, action dim 7)" in result.output
    t = Transitions.load_npz(out)
    steps = [s for s in TraceReader(two_episodes).records() if isinstance(s, EnvStep)]
    assert t.obs.tolist() == [list(s.obs) for s in steps]
    assert t.episode.tolist() == [0, 1, 1, 1]


def test_export_selected_episodes_to_jsonl(two_episodes: Path, tmp_path: Path) -> None:
    out = tmp_path / "exp" / "t.jsonl"
    result = run("export", str(two_episodes), "--episodes", "1", "-o", str(out), "--json")
    assert result.exit_code == 0, result.output
    doc = json.loads(result.output)
    assert doc["format"] == "jsonl" and doc["transitions"] == 3 and doc["episodes"] == "1"
    assert doc["arrays"]["obs"] == [[3, 50], "<f4"]
    rows = [json.loads(line) for line in out.read_text().splitlines()]
    assert [r["step"] for r in rows] == [0, 1, 2] and {r["episode"] for r in rows} == {1}


def test_export_format_option_and_ecm_filter(two_episodes: Path, tmp_path: Path) -> None:
    out = tmp_path / "t.data"
    result = run("export", str(two_episodes), "-o", str(out), "--format", "npz", "--ecm", "nobody")
    assert result.exit_code == 0, result.output
    with np.load(out, allow_pickle=False) as data:
        assert data["obs"].shape == (0, 0)


def test_export_refuses_to_overwrite(two_episodes: Path, tmp_path: Path) -> None:
    # Invariant 3.
    out = tmp_path / "t.npz"
    out.write_bytes(b"old")
    result = run("export", str(two_episodes), "-o", str(out))
    assert result.exit_code == 5
    assert result.output.strip() == f"error [conflict]: output already exists: {out} (pass --force to replace it)"
    assert out.read_bytes() == b"old"
    assert run("export", str(two_episodes), "-o", str(out), "--force").exit_code == 0
    assert len(Transitions.load_npz(out)) == 4


def test_export_of_a_crashed_file_needs_allow_incomplete(unfinished: Path, tmp_path: Path) -> None:
    result = run("export", str(unfinished), "-o", str(tmp_path / "t.npz"))
    assert result.exit_code == 8
    assert result.output.startswith("error [corrupt]: trace file")
    assert "capevo trace recover" in result.output
    result = run("export", str(unfinished), "-o", str(tmp_path / "t.npz"), "--allow-incomplete")
    assert result.exit_code == 0, result.output
    assert len(Transitions.load_npz(tmp_path / "t.npz")) == 2


def test_recover_command(unfinished: Path) -> None:
    result = run("recover", str(unfinished))
    assert result.exit_code == 0, result.output
    out = unfinished.with_name("crashed.recovered.mcap")
    assert f"recovered {len(one_of_each())} messages into {out}" in result.output
    assert "the source stopped at byte" in result.output and "file ends without a footer" in result.output
    assert TraceReader(out).topic_counts()["/env/step"] == 2
    again = run("recover", str(unfinished), "--json")
    assert again.exit_code == 5 and "already exists" in again.output
    forced = run("recover", str(unfinished), "--force", "--json", "-o", str(out))
    doc = json.loads(forced.output)
    assert doc["complete"] is False and doc["messages"] == len(one_of_each())


@pytest.mark.parametrize("command", [["summary"], ["export"], ["recover"]])
def test_missing_file_is_a_clean_error(command: list[str], tmp_path: Path) -> None:
    # Invariant 1: one line, mapped exit code, no traceback.
    missing = tmp_path / "nope.mcap"
    result = CliRunner().invoke(trace, [*command, str(missing)])
    assert result.exit_code == 4
    assert result.output == f"error [not_found]: trace file not found: {missing}\n"
    assert result.exception is None or isinstance(result.exception, SystemExit)


@pytest.mark.parametrize("command", [["summary"], ["export"], ["recover"]])
def test_non_mcap_file_is_a_clean_error(command: list[str], tmp_path: Path) -> None:
    bogus = tmp_path / "notes.txt"
    bogus.write_text("not a trace")
    result = CliRunner().invoke(trace, [*command, str(bogus)])
    assert result.exit_code == 3
    assert result.output == f"error [invalid]: not an MCAP file (bad magic bytes): {bogus}\n"


def test_bad_episode_selection_is_a_clean_error(two_episodes: Path) -> None:
    result = run("export", str(two_episodes), "--episodes", "2-1")
    assert result.exit_code == 3
    assert result.output.startswith("error [invalid]: bad episode selection '2-1'")


def test_mcap_without_capevo_metadata(tmp_path: Path) -> None:
    from mcap.writer import Writer

    path = tmp_path / "foreign.mcap"
    with path.open("wb") as f:
        w = Writer(f)
        w.start()
        w.finish()
    result = run("summary", str(path))
    assert result.exit_code == 8
    assert "not a capevo trace: no 'capevo.run' metadata record" in result.output


def test_python_dash_m(two_episodes: Path, tmp_path: Path) -> None:
    ok = subprocess.run(
        [sys.executable, "-m", "capevo.cli.trace", "summary", str(two_episodes), "--json"],
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert ok.returncode == 0, ok.stderr
    assert json.loads(ok.stdout)["run_id"] == "run-1"
    bad = subprocess.run(
        [sys.executable, "-m", "capevo.cli.trace", "summary", str(tmp_path / "nope.mcap")],
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert bad.returncode == 4
    assert "Traceback" not in bad.stderr
    assert bad.stderr.strip() == f"error [not_found]: trace file not found: {tmp_path / 'nope.mcap'}"


def test_errors_map_the_same_inside_a_capevo_group(tmp_path: Path) -> None:
    # The lead registers `trace` into the main `capevo` group; errors keep their line and code there.
    from capevo.cli import CapevoGroup

    root = CapevoGroup(name="capevo")
    root.add_command(trace)
    missing = tmp_path / "nope.mcap"
    result = CliRunner().invoke(root, ["trace", "recover", str(missing)])
    assert result.exit_code == 4
    assert result.output == f"error [not_found]: trace file not found: {missing}\n"
    helped = CliRunner().invoke(root, ["trace", "--help"])
    assert helped.exit_code == 0
    for command in ("summary", "export", "recover"):
        assert command in helped.output
