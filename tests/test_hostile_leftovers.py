"""The hostile run's leftovers: a service account's install, a Ctrl-C a library swallows,
profiles validated at load, impossible CFA patterns, transparent frames, frames that are
not regular files, headerless tables and output to standard output."""
import os
import shutil
import signal
import subprocess
import sys
import tempfile
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]


def _as_service_account() -> list[str]:
    """A command prefix that runs Python as a user who cannot write the package's folder
    and has no home (``HOME=/nonexistent``): as ``nobody`` when the tests run as root."""
    if hasattr(os, "getuid") and os.getuid() == 0:
        setpriv = shutil.which("setpriv")
        if setpriv is None:
            pytest.skip("running as root without setpriv: cannot become another user")
        return [setpriv, "--reuid=nobody", "--regid=nogroup", "--clear-groups"]
    return []


def test_a_service_account_without_a_home_merges_with_a_read_only_install():
    """A root-owned install (the package's folders not writable by the user) and
    ``HOME=/nonexistent``: the kernels cache elsewhere or not at all; never a traceback
    (numba's 'no locator available')."""
    base = Path(tempfile.mkdtemp())  # not under pytest's private tmp_path: the other user must reach it
    try:
        base.chmod(0o755)
        install, work = base / "site", base / "work"
        shutil.copytree(ROOT / "hdrmerge_cli", install / "hdrmerge_cli",
                        ignore=shutil.ignore_patterns("__pycache__"))
        work.mkdir()
        work.chmod(0o777)
        for p in [install, *install.rglob("*")]:
            p.chmod(0o555 if p.is_dir() else 0o444)
        prefix = _as_service_account()
        env = {"PATH": os.environ.get("PATH", "/usr/bin:/bin"), "HOME": "/nonexistent",
               "PYTHONPATH": str(install), "TMPDIR": str(work)}
        probe = subprocess.run(prefix + [sys.executable, "-c", "import numpy, numba"], env=env, capture_output=True)
        if probe.returncode != 0:
            pytest.skip(f"the other user cannot run this Python: {probe.stderr.decode()[-200:]}")

        def run(*args):
            return subprocess.run(prefix + [sys.executable, "-m", "hdrmerge_cli", *args], env=env, cwd=work,
                                  capture_output=True, text=True)

        sim = run("simulate", "-o", str(work / "sim"), "--size", "48x32", "--frames", "3", "-q")
        assert sim.returncode == 0 and "Traceback" not in sim.stderr, sim.stderr
        merged = run("merge", *sorted(str(p) for p in (work / "sim").glob("frame_*.dng")), "-o", str(work / "m.exr"))
        assert merged.returncode == 0 and "Traceback" not in merged.stderr, merged.stderr
        assert (work / "m.exr").is_file()
    finally:
        for p in base.rglob("*"):
            if p.is_dir():
                p.chmod(0o755)
        shutil.rmtree(base, ignore_errors=True)


def test_a_ctrl_c_a_library_swallows_still_stops_the_merge(tmp_path, monkeypatch, dng_bracket):
    """A SIGINT whose exception a bare ``except:`` swallowed (as in some import-time probe)
    is noted by the handler: the merge commits nothing and exits 130 with the one line."""
    from click.testing import CliRunner

    from hdrmerge_cli.cli import cli
    from hdrmerge_cli.core import errors
    from hdrmerge_cli.pipeline import run

    merge_frames = run.merge_frames

    def swallowing(*args, **kwargs):
        try:
            errors.raise_terminated(signal.SIGINT, None)
        except BaseException:  # a library's bare except
            pass
        return merge_frames(*args, **kwargs)

    monkeypatch.setattr(run, "merge_frames", swallowing)
    frames = sorted(str(p) for p in dng_bracket[0].glob("frame_*.dng"))
    try:
        result = CliRunner().invoke(cli, ["merge", *frames, "-o", str(tmp_path / "out.exr")])
    finally:
        errors.RECEIVED.clear()
    assert result.exit_code == 130, result.output
    assert "stopped by SIGINT" in result.stderr
    assert list(tmp_path.iterdir()) == []
