"""Session store: atomic frames, append-only journal, name validation, no clobbering."""
import json

import pytest

from rig.files.session import Session, SessionError, atomic_write_bytes, validate_session_name


@pytest.mark.parametrize("name", ["../evil", "a/b", ".hidden", "", "x" * 65, "a..b", "sp ace"])
def test_bad_session_names_refused(name):
    with pytest.raises(SessionError):
        validate_session_name(name)


@pytest.mark.parametrize("name", ["s1", "2026-11-21_marble.A", "run_7"])
def test_good_session_names(name):
    assert validate_session_name(name) == name


def _new(tmp_path, name="s1"):
    return Session.create(tmp_path, name, config={"k": 1}, devices={"sphere": {"model": "m"}},
                          plan=[{"index": 0}], geometry={"key_led": 3}, truth=None)


def test_create_writes_manifest_and_start_event(tmp_path):
    s = _new(tmp_path)
    m = json.loads((s.root / "manifest.json").read_text())
    assert m["format"] == "sssrig-session" and m["format_version"] == 1
    assert m["config"] == {"k": 1} and m["geometry"] == {"key_led": 3}
    assert [e["type"] for e in s.events()] == ["start"]
    with pytest.raises(SessionError, match="exists"):
        _new(tmp_path)


def test_frames_are_copied_with_hash_and_never_overwritten(tmp_path):
    s = _new(tmp_path)
    src = tmp_path / "drop.dng"
    src.write_bytes(b"raw-bytes-1")
    rec = s.add_frame(3, src, pattern="x", polarization="cross", exposure_s=0.02, t_trigger="t")
    assert (s.root / rec.file).read_bytes() == b"raw-bytes-1"
    assert s.frame("x", "cross").sha256 == rec.sha256
    assert s.completed_steps() == {3}
    src.write_bytes(b"other")
    with pytest.raises(SessionError, match="refusing to overwrite"):
        s.add_frame(3, src, pattern="x", polarization="cross", exposure_s=0.02, t_trigger="t")
    assert (s.root / rec.file).read_bytes() == b"raw-bytes-1"
    assert s.verify() == []
    (s.root / rec.file).write_bytes(b"tampered")
    assert "SHA-256 differs" in s.verify()[0]


def test_torn_journal_line_is_skipped(tmp_path):
    s = _new(tmp_path)
    s.add_survey(1, "object_top", (0.0, 0.0, 10.0), None)
    with open(s.root / "events.jsonl", "a") as fh:
        fh.write('{"t": "x", "type": "frame", "ste')       # a crash mid-write
    reopened = Session.open(s.root)
    assert reopened.surveys()["object_top"]["xyz_mm"] == [0.0, 0.0, 10.0]
    assert reopened.frames() == []


def test_open_refuses_non_sessions_and_other_versions(tmp_path):
    with pytest.raises(SessionError, match="no manifest.json"):
        Session.open(tmp_path)
    s = _new(tmp_path)
    m = json.loads((s.root / "manifest.json").read_text())
    m["format_version"] = 99
    atomic_write_bytes(s.root / "manifest.json", json.dumps(m).encode(), overwrite=True)
    with pytest.raises(SessionError, match="format_version"):
        Session.open(s.root)


def test_atomic_write_leaves_no_temporary_files(tmp_path):
    atomic_write_bytes(tmp_path / "a.bin", b"1")
    atomic_write_bytes(tmp_path / "a.bin", b"2", overwrite=True)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["a.bin"]
    assert (tmp_path / "a.bin").read_bytes() == b"2"


def test_manifest_records_software_version_and_request(tmp_path):
    from importlib.metadata import version
    s = Session.create(tmp_path, "v", config={}, devices={}, plan=[], request={"estimate": ["gradients"]})
    m = s.manifest
    assert m["software_version"] == version("sssrig") and m["request"] == {"estimate": ["gradients"]}


def test_recover_moves_unjournalled_frames_aside_and_never_deletes(tmp_path):
    s = _new(tmp_path)
    src = tmp_path / "drop.dng"
    src.write_bytes(b"journalled")
    kept = s.add_frame(2, src, pattern="full", polarization="cross", exposure_s=0.02, t_trigger="t")
    # a crash between the atomic copy and the journal line, and one in the middle of a copy
    (s.root / "frames" / "0005_x_cross.dng").write_bytes(b"copied, not journalled")
    (s.root / "frames" / ".0007_y_cross.dng.123.tmp").write_bytes(b"half a fr")
    moved = s.recover()
    assert len(moved) == 2
    orphans = sorted(p.name for p in (s.root / "frames" / "orphans").iterdir())
    assert orphans == ["0005_x_cross.dng", "0007_y_cross.dng.123.tmp"]
    assert (s.root / "frames" / "orphans" / "0005_x_cross.dng").read_bytes() == b"copied, not journalled"
    assert sorted(p.name for p in (s.root / "frames").glob("*.dng")) == [kept.file.split("/")[1]]
    assert [e["type"] for e in s.events()][-1] == "recovered"
    assert s.recover() == [] and s.verify() == []


def test_retaking_a_frame_whose_copy_was_orphaned(tmp_path):
    s = _new(tmp_path)
    (s.root / "frames" / "0004_z_cross.dng").write_bytes(b"from the killed run")
    src = tmp_path / "drop.dng"
    src.write_bytes(b"retaken")
    rec = s.add_frame(4, src, pattern="z", polarization="cross", exposure_s=0.02, t_trigger="t")
    assert (s.root / rec.file).read_bytes() == b"retaken"
    assert (s.root / "frames" / "orphans" / "0004_z_cross.dng").read_bytes() == b"from the killed run"


def test_status_follows_start_stop_and_restart(tmp_path):
    s = _new(tmp_path)
    assert s.status() == "interrupted"
    s.stop("paused", "SIGINT")
    assert s.status() == "paused"
    s.append_event({"type": "restart"})
    assert s.status() == "interrupted"
    s.stop("complete")
    assert s.status() == "complete"
    with pytest.raises(ValueError, match="stop status"):
        s.stop("finished")
