"""The log goes to the journal's native protocol only when systemd connected our stderr to
the journal ($JOURNAL_STREAM names that very file), to the stream otherwise. No journald
is needed: the journal handler's sender is replaced by a recorder."""

from __future__ import annotations

import logging
import os
from pathlib import Path

import pytest
from systemd.journal import JournalHandler

from robotd.app.logsetup import configure_logging, journal_wanted, make_handler


@pytest.fixture
def stream(tmp_path: Path):
    with open(tmp_path / "stderr.txt", "w", encoding="utf-8") as f:
        yield f


def _stream_id(f) -> str:
    st = os.fstat(f.fileno())
    return f"{st.st_dev}:{st.st_ino}"


def test_journal_only_when_journal_stream_names_our_stream(stream, tmp_path):
    assert journal_wanted({"JOURNAL_STREAM": _stream_id(stream)}, stream)
    with open(tmp_path / "other.txt", "w", encoding="utf-8") as other:
        # Inherited from a parent whose stderr was the journal, ours redirected elsewhere.
        assert not journal_wanted({"JOURNAL_STREAM": _stream_id(other)}, stream)
    assert not journal_wanted({}, stream)
    assert not journal_wanted({"INVOCATION_ID": "0123456789abcdef"}, stream)  # under systemd, not the journal
    for bad in ("", "12", "a:b", "1:2:3"):
        assert not journal_wanted({"JOURNAL_STREAM": bad}, stream)
    assert not journal_wanted({"JOURNAL_STREAM": _stream_id(stream)}, None)


def test_the_handler_chosen_and_what_it_sends(stream):
    env = {"JOURNAL_STREAM": _stream_id(stream)}
    handler = make_handler(env, stream)
    assert isinstance(handler, JournalHandler)
    sent: list[dict] = []
    handler.send = lambda *message, **fields: sent.append({**fields, "MESSAGE": message[0]})
    logger = logging.getLogger("robotd.test.journal")
    record = logger.makeRecord(logger.name, logging.WARNING, __file__, 1, "base %s lost", ("kobuki",), None)
    handler.handle(record)
    (fields,) = sent
    assert fields["MESSAGE"] == "robotd.test.journal: base kobuki lost"
    assert fields["PRIORITY"] == "4"  # warning: journalctl -p warning shows it
    assert fields["SYSLOG_IDENTIFIER"] == "robotd"
    assert fields["LOGGER"] == "robotd.test.journal"

    plain = make_handler({}, stream)
    assert type(plain) is logging.StreamHandler and plain.stream is stream
    plain.handle(record)
    stream.flush()
    line = Path(stream.name).read_text(encoding="utf-8")
    assert line.endswith(" WARNING robotd.test.journal: base kobuki lost\n")


def test_configure_logging_installs_once(stream, monkeypatch):
    root = logging.getLogger()
    monkeypatch.setattr(root, "handlers", [])
    monkeypatch.setattr(root, "level", root.level)
    handler = configure_logging("debug", env={}, stream=stream)
    assert root.handlers == [handler] and root.level == logging.DEBUG
    assert configure_logging("error", env={}, stream=stream) is None  # already configured
    assert root.handlers == [handler] and root.level == logging.DEBUG
