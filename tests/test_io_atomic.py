"""Outputs as one transaction: all or nothing, no clobbering of a file that
appeared meanwhile, outputs that collide with each other or with an input refused first,
errors naming the user's path, SIGTERM cleaned up like SIGINT."""
import os
import signal
import subprocess
import time
from pathlib import Path

import pytest

from conftest import frames_of
from hdrmerge_cli.core.errors import HdrMergeError
from hdrmerge_cli.io.atomic import atomic_paths


def test_all_outputs_appear_together_or_none(tmp_path):
    a, b = tmp_path / "a.txt", tmp_path / "b.txt"
    with pytest.raises(RuntimeError):
        with atomic_paths([a, b], False) as (ta, tb):
            Path(ta).write_text("a")
            raise RuntimeError("stop")
    assert sorted(os.listdir(tmp_path)) == []
    with atomic_paths([a, b], False) as (ta, tb):
        Path(ta).write_text("a")
        Path(tb).write_text("b")
    assert a.read_text() == "a" and b.read_text() == "b" and sorted(os.listdir(tmp_path)) == ["a.txt", "b.txt"]


def test_a_file_that_appears_meanwhile_is_not_clobbered_and_nothing_half_done(tmp_path):
    a, b = tmp_path / "a.txt", tmp_path / "b.txt"
    with pytest.raises(HdrMergeError, match="b.txt: appeared"):
        with atomic_paths([a, b], False) as (ta, tb):
            Path(ta).write_text("mine")
            Path(tb).write_text("mine")
            b.write_text("theirs")  # a concurrent run finished first
    assert b.read_text() == "theirs" and not a.exists()
    assert sorted(os.listdir(tmp_path)) == ["b.txt"]


def test_a_failed_commit_restores_the_files_it_replaced(tmp_path, monkeypatch):
    a, b = tmp_path / "a.txt", tmp_path / "b.txt"
    a.write_text("old a")
    real_link = os.link

    def link(src, dst):
        if str(dst).endswith("b.txt"):
            raise PermissionError(13, "Permission denied", str(dst))
        return real_link(src, dst)

    monkeypatch.setattr(os, "link", link)
    monkeypatch.setattr(os, "replace", lambda s, d, real=os.replace: (_ for _ in ()).throw(
        PermissionError(13, "Permission denied", str(d))) if str(d).endswith("b.txt") else real(s, d))
    with pytest.raises(HdrMergeError, match="b.txt: cannot write"):
        with atomic_paths([a, b], True) as (ta, tb):
            Path(ta).write_text("new a")
            Path(tb).write_text("new b")
    assert a.read_text() == "old a" and sorted(os.listdir(tmp_path)) == ["a.txt"]


def test_errors_while_writing_name_the_users_path(tmp_path):
    out = tmp_path / "x.txt"
    with pytest.raises(HdrMergeError) as info:
        with atomic_paths([out], False) as (tmp,):
            raise OSError(28, "No space left on device", tmp)
    assert str(info.value) == f"{out}: cannot write (No space left on device)" and ".part" not in str(info.value)


@pytest.mark.parametrize("which", ["profile", "preview", "input"])
def test_colliding_outputs_are_refused_before_any_work(run, tmp_path, jpeg_bracket, which):
    folder, meta = jpeg_bracket
    frames = frames_of(folder, meta)
    out = tmp_path / "m.exr"
    extra = {"profile": ["--profile-out", out],
             "preview": ["--profile-out", tmp_path / "p.png", "--preview", tmp_path / "p.png"],
             "input": []}[which]
    target = frames[0].with_suffix(".exr") if which == "input" else out
    if which == "input":  # an output that is an input, even with --overwrite
        os.symlink(frames[0], target)
    before = target.read_bytes() if target.exists() else None
    proc = run("merge", *frames, "--crf", "srgb", "-o", target, "--overwrite", *extra, check=False)
    assert proc.returncode == 1 and ("two outputs" in proc.stderr or "is an input" in proc.stderr), proc.stderr
    if before is not None:
        assert target.read_bytes() == before


@pytest.mark.parametrize("sig", [signal.SIGTERM, signal.SIGHUP, signal.SIGINT])
def test_a_signal_mid_write_removes_the_temporaries(run, tmp_path_factory, sig):
    """SIGTERM/SIGHUP/SIGINT (Ctrl-C) while the outputs are being written (a temporary
    exists): every temporary removed, no output, exit 128 + n (130 for Ctrl-C, not click's
    "Aborted!" and 1), one line."""
    from conftest import _command

    folder = tmp_path_factory.mktemp("big")
    run("simulate", "-o", folder, "-q", "--size", "2400x1600", "--frames", "3", "--seed", "1")
    out_dir = tmp_path_factory.mktemp("out")
    proc = subprocess.Popen(_command() + ["merge", *map(str, sorted(folder.glob("frame_*.dng"))), "-o",
                                          str(out_dir / "m.exr"), "--preview", str(out_dir / "m.jpg"), "--align", "off"],
                            stderr=subprocess.PIPE, text=True)
    deadline = time.monotonic() + 120
    while not any(".part" in n for n in os.listdir(out_dir)):
        assert proc.poll() is None and time.monotonic() < deadline, "the merge ended before writing"
        time.sleep(0.005)
    proc.send_signal(sig)
    _, err = proc.communicate(timeout=60)
    if proc.returncode == 0:
        pytest.skip("the merge finished writing before the signal arrived")
    assert proc.returncode == 128 + sig and "Traceback" not in err, err
    assert len(err.strip().splitlines()) == 1 and os.listdir(out_dir) == []


def test_a_signal_right_after_a_temporary_is_created_leaves_nothing(tmp_path, monkeypatch):
    """The temporary's name is listed before the file exists: a signal that unwinds the
    moment the file is created (here: the close right after it raises Terminated, as a
    SIGTERM handler would when the interpreter gets back to this thread) leaves no file."""
    from hdrmerge_cli.core.errors import Terminated
    from hdrmerge_cli.io import atomic

    real_close = os.close
    calls = []

    def close(fd):
        real_close(fd)
        calls.append(fd)
        if len(calls) == 2:  # the second output's temporary was just created
            raise Terminated(signal.SIGTERM)

    monkeypatch.setattr(atomic.os, "close", close)
    with pytest.raises(Terminated):
        with atomic.atomic_paths([tmp_path / "a.exr", tmp_path / "a.profile.json"], overwrite=False):
            pass
    assert os.listdir(tmp_path) == []


def test_a_stop_signal_during_the_clean_up_still_removes_every_temporary(tmp_path, monkeypatch):
    """A stop signal (here Ctrl-C) raised while the transaction removes its temporaries
    (right after the first) does not leave the others behind: all are removed, then it
    unwinds."""
    import hdrmerge_cli.io.atomic as atomic

    real_unlink, calls = os.unlink, []

    def unlink(path):
        real_unlink(path)
        calls.append(path)
        if len(calls) == 1:
            raise KeyboardInterrupt  # as a signal handler would, between two removals

    outs = [tmp_path / "a.exr", tmp_path / "a.profile.json", tmp_path / "a.jpg"]
    with pytest.raises(KeyboardInterrupt):
        with atomic_paths(outs, overwrite=False) as tmps:
            for t in tmps:
                Path(t).write_text("x")
            monkeypatch.setattr(atomic.os, "unlink", unlink)
    monkeypatch.undo()
    assert sorted(p.name for p in tmp_path.iterdir()) == ["a.exr", "a.jpg", "a.profile.json"]
