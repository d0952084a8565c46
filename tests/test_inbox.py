"""The inbox flow's honest outcomes (real Prefect flow runs on the session's test server):
a missing inbox is an error, not an empty inbox; a failed mission fails the parent run
with its name and reason in the state message; finished missions are not redone."""
import json

import pytest

pytestmark = pytest.mark.usefixtures("prefect_harness")


def test_missing_inbox_fails_the_run_naming_the_folder(tmp_path):
    from swathflow.flows.inbox import inbox_flow
    missing = tmp_path / "no-such-inbox"
    state = inbox_flow(str(missing), str(tmp_path / "products"), return_state=True)
    assert state.is_failed(), state
    assert str(missing) in state.message and "does not exist" in state.message
    assert not (tmp_path / "products").exists()


def test_inbox_that_is_a_file_fails_the_run(tmp_path):
    from swathflow.errors import SwathflowError
    from swathflow.flows.inbox import inbox_flow
    inbox = tmp_path / "inbox"
    inbox.write_text("not a folder")
    with pytest.raises(SwathflowError, match="is not a folder"):
        inbox_flow(str(inbox), str(tmp_path / "products"))


def test_empty_inbox_completes_with_nothing_done(tmp_path):
    from swathflow.flows.inbox import inbox_flow
    (tmp_path / "inbox").mkdir()
    (tmp_path / "inbox" / "not-a-mission").mkdir()   # no mission.toml: ignored
    assert inbox_flow(str(tmp_path / "inbox"), str(tmp_path / "out")) == {"done": [],
                                                                         "failed": {}}


def test_broken_mission_fails_the_parent_run_with_its_reason(tmp_path):
    """Two arrivals: one finished earlier (DONE.json, skipped), one whose mission.toml is
    not TOML. The parent run ends Failed and its message names the broken one and why."""
    from swathflow.flows.inbox import inbox_flow
    inbox, products = tmp_path / "inbox", tmp_path / "products"
    (inbox / "flight-bad").mkdir(parents=True)
    (inbox / "flight-bad" / "mission.toml").write_text("this is = = not toml\n")
    (inbox / "flight-old").mkdir()
    (inbox / "flight-old" / "mission.toml").write_text("this is = = not toml either\n")
    (products / "flight-old").mkdir(parents=True)
    (products / "flight-old" / "DONE.json").write_text(json.dumps({"mosaic": "x"}))
    state = inbox_flow(str(inbox), str(products), return_state=True)
    assert state.is_failed(), state
    assert "1 of 1 missions failed" in state.message
    assert "flight-bad" in state.message and "mission.toml" in state.message
    assert "flight-old" not in state.message
    assert not (products / "flight-bad" / "DONE.json").exists()
