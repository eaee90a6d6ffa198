"""Bad inputs: right exit code, one ``error [code]: message`` line on stderr, never a traceback."""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path

import pytest
from cli_support import assert_clean_error, run_capevo
from click.core import ParameterSource
from click.testing import Result
from hypothesis import given
from hypothesis import strategies as st

from capevo.cli import EXIT_CODES, error_line, exit_code_for, resolve_target
from capevo.errors import CapevoError, ErrorCode, Invalid, error_class


def _publish(cli: Callable[..., Result], root: Path, artifact: Path, descriptor: Path, name: str = "reach") -> Result:
    return cli("ecm", "publish", name, "--artifact", artifact, "--descriptor", descriptor, "--root", root)


def test_bad_descriptor_names_the_field(
    cli: Callable[..., Result], root: Path, tmp_path: Path, make_artifact: Callable[[str], Path]
) -> None:
    bad = tmp_path / "bad.yaml"
    bad.write_text("kind: code\ndescription: x\ninterface:\n  inputs: [{name: a, shape: [0]}]\n")
    res = _publish(cli, root, make_artifact("v0"), bad)
    assert res.exit_code == 3
    msg = assert_clean_error(res.stderr, "invalid")
    assert msg.startswith(f"descriptor {str(bad)!r}: interface.inputs[0].shape[0]: ")
    assert "minimum of 1" in msg
    assert res.stdout == ""
    assert not root.exists()  # a refused publish never opens (or creates) the registry


@pytest.mark.parametrize(
    ("text", "field"),
    [
        ("description: no kind\n", "<document>"),
        ("kind: laser\ndescription: x\n", "kind"),
        ("kind: code\ndescription: x\nbogus: 1\n", "<document>"),
        ("kind: code\ndescription: x\norigin: alien\n", "origin"),
        ("kind: code\ndescription: [unclosed\n", "<document>"),
    ],
)
def test_bad_descriptor_variants(
    cli: Callable[..., Result],
    root: Path,
    tmp_path: Path,
    make_artifact: Callable[[str], Path],
    text: str,
    field: str,
) -> None:
    bad = tmp_path / "bad.yaml"
    bad.write_text(text)
    res = _publish(cli, root, make_artifact("v0"), bad)
    assert res.exit_code == 3
    msg = assert_clean_error(res.stderr, "invalid")
    assert msg.startswith(f"descriptor {str(bad)!r}: {field}:"), msg


def test_missing_artifact_file(cli: Callable[..., Result], root: Path, descriptor: Path, tmp_path: Path) -> None:
    res = _publish(cli, root, tmp_path / "nope.zip", descriptor)
    assert res.exit_code == 3
    msg = assert_clean_error(res.stderr, "invalid")
    assert msg == f"--artifact: file {str(tmp_path / 'nope.zip')!r} does not exist"
    assert not root.exists()


def test_missing_descriptor_file(
    cli: Callable[..., Result], root: Path, make_artifact: Callable[[str], Path], tmp_path: Path
) -> None:
    res = _publish(cli, root, make_artifact("v0"), tmp_path / "none.yaml")
    assert res.exit_code == 3
    assert assert_clean_error(res.stderr, "invalid").startswith("--descriptor: file ")


def test_artifact_is_a_directory(cli: Callable[..., Result], root: Path, descriptor: Path, tmp_path: Path) -> None:
    res = _publish(cli, root, tmp_path, descriptor)
    assert res.exit_code == 3
    assert "is a directory" in assert_clean_error(res.stderr, "invalid")


@pytest.mark.parametrize("name", ["Bad/Name", "UPPER", "a*b", "active", "x" * 65, "..", "_lead", "a..b"])
def test_bad_name(
    cli: Callable[..., Result], root: Path, descriptor: Path, make_artifact: Callable[[str], Path], name: str
) -> None:
    res = _publish(cli, root, make_artifact("v0"), descriptor, name=name)
    assert res.exit_code == 3
    msg = assert_clean_error(res.stderr, "invalid")
    assert "ECM name" in msg
    root.mkdir(exist_ok=True)
    for args in (["ecm", "show", name], ["ecm", "history", name], ["ecm", "promote", name, "0"]):
        res = cli(*args, "--root", root)
        assert res.exit_code == 3, args
        assert "ECM name" in assert_clean_error(res.stderr, "invalid")


def test_unknown_ecm(
    cli: Callable[..., Result], root: Path, descriptor: Path, make_artifact: Callable[[str], Path]
) -> None:
    assert _publish(cli, root, make_artifact("v0"), descriptor).exit_code == 0
    for args in (
        ["ecm", "show", "ghost"],
        ["ecm", "history", "ghost"],
        ["ecm", "promote", "ghost", "0"],
        ["ecm", "rollback", "ghost"],
        ["ecm", "pull", "ghost", "-o", str(root.parent / "x")],
    ):
        res = cli(*args, "--root", root)
        assert res.exit_code == 4, (args, res.stderr)
        assert "ghost" in assert_clean_error(res.stderr, "not_found")
    res = cli("ecm", "show", "reach", "--version", "7", "--root", root)
    assert res.exit_code == 4
    assert "reach" in assert_clean_error(res.stderr, "not_found")
    res = cli("ecm", "pull", "reach", "-o", str(root.parent / "x"), "--root", root)  # nothing active yet
    assert res.exit_code == 4
    assert not (root.parent / "x").exists()


def test_missing_root_is_not_found_not_created(cli: Callable[..., Result], tmp_path: Path) -> None:
    where = tmp_path / "nowhere"
    res = cli("ecm", "list", "--root", where)
    assert res.exit_code == 4
    assert "does not exist" in assert_clean_error(res.stderr, "not_found")
    assert not where.exists()


def test_conflict_and_illegal_transition_codes(
    cli: Callable[..., Result], root: Path, descriptor: Path, make_artifact: Callable[[str], Path]
) -> None:
    _publish(cli, root, make_artifact("v0"), descriptor)
    _publish(cli, root, make_artifact("v1"), descriptor)
    assert cli("ecm", "promote", "reach", "0", "--root", root).exit_code == 0
    res = cli("ecm", "promote", "reach", "1", "--expected-active", "1", "--root", root)
    assert res.exit_code == 5
    assert "expected active v1" in assert_clean_error(res.stderr, "conflict")
    res = cli("ecm", "deprecate", "reach", "0", "--root", root)
    assert res.exit_code == 6
    assert "it is active" in assert_clean_error(res.stderr, "illegal_transition")
    res = cli("ecm", "show", "reach", "--json", "--root", root)  # state unchanged by the refusals
    assert '"active_version": 0' in res.stdout


def test_root_and_connect_together_refused(cli: Callable[..., Result], root: Path) -> None:
    res = cli("ecm", "list", "--root", root, "--connect", "tcp/127.0.0.1:1")
    assert res.exit_code == 3
    assert "exactly one of --root and --connect" in assert_clean_error(res.stderr, "invalid")
    res = cli("ecm", "list", env={"CAPEVO_ROOT": str(root), "CAPEVO_CONNECT": "tcp/127.0.0.1:1"})
    assert res.exit_code == 3
    assert "environment" in assert_clean_error(res.stderr, "invalid")


def test_usage_errors_exit_2(cli: Callable[..., Result], root: Path) -> None:
    assert cli("ecm", "promote", "reach", "--root", root).exit_code == 2  # missing VERSION
    assert cli("ecm", "promote", "reach", "-1", "--root", root).exit_code == 2
    assert cli("ecm", "frobnicate").exit_code == 2


def test_errors_in_a_real_process_have_no_traceback(tmp_path: Path, descriptor: Path) -> None:
    proc = run_capevo(
        [
            "ecm",
            "publish",
            "reach",
            "--artifact",
            tmp_path / "nope",
            "--descriptor",
            descriptor,
            "--root",
            tmp_path / "r",
        ]
    )
    assert proc.returncode == 3
    assert_clean_error(proc.stderr, "invalid")
    proc = run_capevo(["ecm", "show", "ghost", "--root", tmp_path])
    assert proc.returncode == 4
    assert assert_clean_error(proc.stderr, "not_found") == "no ECM named 'ghost'"


# --- the exit-code map and the selection rule -------------------------------------------------
def test_every_error_code_has_a_distinct_exit_code() -> None:
    assert set(EXIT_CODES) == set(ErrorCode)
    values = list(EXIT_CODES.values())
    assert len(set(values)) == len(values)
    assert 0 not in values and 2 not in values  # 0 is success, 2 is click's usage error
    assert all(0 < v < 126 for v in values)
    for code in ErrorCode:
        assert exit_code_for(error_class(code)("x")) == EXIT_CODES[code]


@given(st.text(max_size=200))
def test_error_line_is_always_one_line(message: str) -> None:
    line = error_line(Invalid(message))
    assert "\n" not in line and "\r" not in line
    assert line.startswith("error [invalid]: ")


@given(st.text(alphabet=st.characters(blacklist_categories=["Cs"]), min_size=1, max_size=50))
def test_error_line_keeps_the_words(message: str) -> None:
    assert error_line(CapevoError(message)).split()[2:] == message.split()


_SOURCES = [ParameterSource.COMMANDLINE, ParameterSource.ENVIRONMENT, ParameterSource.DEFAULT]


@given(
    root_src=st.sampled_from(_SOURCES),
    connect=st.lists(st.sampled_from(["tcp/127.0.0.1:7447", "tcp/10.0.0.1:7447", " "]), max_size=3),
    connect_src=st.sampled_from(_SOURCES[:2]),
)
def test_resolve_target_rule(root_src: ParameterSource, connect: list[str], connect_src: ParameterSource) -> None:
    rank = {ParameterSource.COMMANDLINE: 2, ParameterSource.ENVIRONMENT: 1, ParameterSource.DEFAULT: 0}
    real = tuple(c for c in connect if c.strip())
    kwargs = {"root": "r", "root_source": root_src, "connect": tuple(connect), "connect_source": connect_src}
    if real and rank[root_src] == rank[connect_src]:
        with pytest.raises(Invalid) as info:
            resolve_target(**kwargs)
        assert info.value.code is ErrorCode.INVALID
        return
    got_root, got_connect = resolve_target(**kwargs)
    if not real or rank[root_src] > rank[connect_src]:
        assert (got_root, got_connect) == (Path("r"), ())
    else:
        assert (got_root, got_connect) == (None, real)


def test_password_is_redacted_from_error_messages(cli: Callable[..., Result]) -> None:
    # The endpoint quotes the password back in the error; the CLI must scrub it.
    secret = "zz-s3cret-pw"
    res = cli("ecm", "list", "--connect", f"tcp/{secret}:99999", "--user", "u", "--password", secret, "--timeout", "1")
    assert res.exit_code in (3, 10)
    assert secret not in res.stderr and "****" in res.stderr
    res = cli(
        "ecm",
        "list",
        "--connect",
        f"tcp/{secret}:99999",
        "--user",
        "u",
        "--timeout",
        "1",
        env={"CAPEVO_PASSWORD": secret},
    )
    assert secret not in res.stderr and "****" in res.stderr


@pytest.mark.parametrize(
    "command",
    [
        ("runtime", "serve", "--connect", "tcp/127.0.0.1:9", "--task", "T1", "--episodes", "1"),
        ("evolve", "--task", "T1", "--root", "{reg}"),
        ("learner", "serve", "--ecm", "pick.reach", "--modality", "il", "--root", "{reg}", "--once"),
    ],
)
def test_an_unknown_envelope_is_refused_before_anything_starts(
    cli: Callable[..., Result], tmp_path: Path, command: tuple[str, ...]
) -> None:
    reg = tmp_path / "reg"
    res = cli(*(c.format(reg=reg) for c in command), "--phi", "papr")
    assert res.exit_code == 3, res.stderr
    msg = assert_clean_error(res.stderr, "invalid")
    assert msg == "phi: expected one of task, paper or a Φ YAML file, got 'papr'"
    assert not reg.exists()


@pytest.mark.parametrize(
    ("extra", "message"),
    [
        (("--root", "{reg}", "--modality", "code"), "--evaluate-on-workers needs --connect"),
        (("--connect", "tcp/127.0.0.1:9", "--modality", "il"), "--evaluate-on-workers runs code learners' samples"),
    ],
)
def test_evaluating_samples_on_workers_needs_a_network_and_a_code_learner(
    cli: Callable[..., Result], tmp_path: Path, extra: tuple[str, ...], message: str
) -> None:
    reg = tmp_path / "reg"
    args = ("learner", "serve", "--ecm", "pick.reach", "--once", "--evaluate-on-workers", *extra)
    res = cli(*(a.format(reg=reg) for a in args))
    assert res.exit_code == 3, res.stderr
    assert assert_clean_error(res.stderr, "invalid").startswith(message)
    assert not reg.exists()
