"""The server-abuse section of the bad-inputs bench (``omniscs.bench.server_abuse.SERVER_CASES``): every hostile
request or flood is refused cleanly, takes no session slot, and leaves the other token served at once."""
from __future__ import annotations

import pytest

from omniscs.bench.server_abuse import (CLOSED, SERVER_CASES, ServerCase, classify_server, run_server_case,
                                        server_markdown, tiny_world)


@pytest.fixture(scope="module")
def world(tmp_path_factory):
    return tiny_world(tmp_path_factory.mktemp("server-abuse"))


@pytest.mark.parametrize("case", SERVER_CASES, ids=[c.name for c in SERVER_CASES])
def test_every_server_abuse_is_refused_cleanly(case, world):
    outcome = run_server_case(case, *world)
    assert outcome.outcome == "clean", outcome


def test_the_classification_names_what_went_wrong():
    case = ServerCase("x", lambda p: [], frozenset({422}))
    assert classify_server(case, [422, 500], 0, "") == "server error"
    assert classify_server(case, [422, 200], 0, "") == "accepted"
    assert classify_server(case, [422, 413], 0, "") == "other"
    assert classify_server(case, [422], 1, "") == "took a slot"
    assert classify_server(case, [422], 0, "reset: 429 after 0.01 s") == "starved the bystander"
    assert classify_server(ServerCase("y", lambda p: [], frozenset({CLOSED})), [CLOSED], 0, "") == "clean"


def test_the_section_reads_as_a_table():
    section = {"limits": {"max_sessions": 8, "requests_per_s": 20.0, "request_burst": 40, "body_timeout_s": 0.5},
               "tried": 1, "counts": {"clean": 1} | dict.fromkeys(("server error", "hang", "accepted", "took a slot",
                                                                   "starved the bystander", "other"), 0),
               "cases": [{"case": "c", "outcome": "clean", "statuses": (422, 422, CLOSED), "abuser_sessions": 0,
                          "bystander": ""}]}
    text = "\n".join(server_markdown(section))
    assert "## Server abuse" in text and "| c | clean | 422 x2, closed | 0 | served |" in text
