"""`omniscs closedloop serve`'s own checks, before any scene is loaded: tokens from a file or the environment (not
only the command line, which other local users can read), an unknown host or a port in use as one line."""
from __future__ import annotations

import socket

import pytest
from typer.testing import CliRunner

from omniscs.cli import app
from omniscs.cli.closedloop import TOKENS_ENV, check_bindable, server_tokens
from omniscs.errors import OmniscsError

runner = CliRunner()


def test_tokens_come_from_the_command_line_a_file_and_the_environment(tmp_path):
    f = tmp_path / "tokens"
    f.write_text("# team tokens\nalpha\n\n  beta  \n")
    assert server_tokens(["cli"], f, "gamma,delta\nalpha") == ["alpha", "beta", "cli", "delta", "gamma"]


@pytest.mark.parametrize("make, message", [
    (lambda p: None, "needs at least one auth token"),
    (lambda p: p, "is not a file"),                                   # a folder
    (lambda p: (p / "t").write_bytes(b"\xff\xfe") and p / "t", "cannot be read as text"),
    (lambda p: (p / "t").write_text("# only a comment\n") and p / "t", "needs at least one auth token"),
    (lambda p: (p / "t").write_text("a\x07b\n") and p / "t", "printable"),
])
def test_a_bad_token_source_is_one_clear_error(tmp_path, make, message):
    with pytest.raises(OmniscsError, match=message):
        server_tokens([], make(tmp_path), None)


def test_an_unresolvable_host_or_a_port_in_use_is_one_line_before_any_work():
    with pytest.raises(OmniscsError, match="does not resolve"):
        check_bindable("no-such-host.invalid", 8065)
    with socket.socket() as held:
        held.bind(("127.0.0.1", 0))
        held.listen()
        with pytest.raises(OmniscsError, match=r"cannot serve on 127\.0\.0\.1:\d+: .*choose another --port"):
            check_bindable("127.0.0.1", held.getsockname()[1])


@pytest.mark.parametrize("port", ["70000", "0", "-1"])
def test_a_port_out_of_range_is_refused_by_the_option(port):
    result = runner.invoke(app, ["closedloop", "serve", "--scenario", "s/log", "--token", "t", "--port", port])
    assert result.exit_code == 2 and "--port" in result.output


def test_serve_without_any_token_says_where_tokens_may_come_from(monkeypatch):
    monkeypatch.delenv(TOKENS_ENV, raising=False)
    result = runner.invoke(app, ["closedloop", "serve", "--scenario", "s/log"])
    assert isinstance(result.exception, OmniscsError) and "--token-file" in str(result.exception)


@pytest.mark.parametrize("argv, option", [
    (["--sessions-per-token", "33"], "--sessions-per-token"),               # more than --max-sessions (32)
    (["--max-sessions", "4", "--sessions-per-token", "5"], "--sessions-per-token"),
    (["--sessions-per-token", "0"], "--sessions-per-token"),
    (["--max-sessions", "0"], "--max-sessions"),
    (["--requests-per-s", "0"], "--requests-per-s"),
    (["--requests-per-s", "nan"], "--requests-per-s"),
])
def test_server_limits_out_of_range_are_refused_before_any_scene_is_loaded(argv, option):
    result = runner.invoke(app, ["closedloop", "serve", "--scenario", "s/log", "--token", "t", *argv])
    assert result.exit_code == 2 and option in result.output, result.output
