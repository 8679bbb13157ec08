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


@pytest.mark.parametrize("pattern", [[7, 7, 7, 7], [0, 0, 0, 0], [1, 1, 1, 1]])
def test_a_mosaic_whose_cfa_pattern_is_no_bayer_pattern_is_refused(tmp_path, pattern):
    """A CFA DNG whose CFAPattern names no colour, or one colour only, is refused in one
    line naming the file and the pattern (it used to merge as a 1-channel Y image)."""
    import numpy as np
    from click.testing import CliRunner

    from hdrmerge_cli.cli import cli
    from hdrmerge_cli.io.dng_integer import write_dng

    frames = []
    for k, t in enumerate((0.01, 0.04)):
        frames.append(str(tmp_path / f"f{k}.dng"))
        mosaic = np.random.default_rng(k).integers(100, 4000, (32, 48)).astype(np.uint16)
        write_dng(frames[-1], mosaic, pattern=pattern, black=64, white=4095, exposure_time=t)
    result = CliRunner().invoke(cli, ["merge", *frames, "-o", str(tmp_path / "out.exr")])
    assert result.exit_code == 1, result.output
    assert result.stderr.startswith(f"hdrmerge-cli: error: {frames[0]}: a colour filter (CFA) mosaic whose CFAPattern")
    assert "Bayer" in result.stderr and len(result.stderr.strip().splitlines()) == 1
    assert not (tmp_path / "out.exr").exists()


@pytest.mark.skipif(not hasattr(os, "mkfifo"), reason="no FIFOs on this system")
def test_a_fifo_given_as_a_frame_is_named_as_what_it_is(tmp_path, jpeg_bracket):
    """A FIFO exists: it is 'not a regular file', not 'no such file' (and is never opened,
    so the command does not block on it)."""
    from click.testing import CliRunner

    from conftest import frames_of
    from hdrmerge_cli.cli import cli

    fifo = tmp_path / "frame.jpg"
    os.mkfifo(fifo)
    folder, meta = jpeg_bracket
    for argv in (["merge", str(fifo), *map(str, frames_of(folder, meta)), "-o", str(tmp_path / "out.exr")], ["info", str(fifo)]):
        result = CliRunner().invoke(cli, argv)
        assert result.exit_code == 1, result.output
        assert result.stderr.strip() == (f"hdrmerge-cli: error: {fifo}: not a regular file (a pipe, socket or "
                                         "device); a frame is a RAW or image file")


@pytest.mark.parametrize("argv", [["merge", "F", "-o", "-"], ["estimate-crf", "F", "-o", "-"],
                                  ["calibrate-noise", "F", "-o", "-"], ["weights-lut", "-o", "-", "--times", "1,2"],
                                  ["simulate", "-o", "-"]])
def test_output_to_standard_output_is_refused_as_such(tmp_path, jpeg_bracket, argv):
    """``-o -`` is a usage error that says standard output is not supported and what to give
    instead, for every command with ``-o`` (not a complaint about the file name's suffix)."""
    from click.testing import CliRunner

    from conftest import frames_of
    from hdrmerge_cli.cli import cli

    folder, meta = jpeg_bracket
    frame = str(frames_of(folder, meta)[0])
    result = CliRunner().invoke(cli, [frame if a == "F" else a for a in argv])
    assert result.exit_code == 2, result.output
    assert "writing to standard output is not supported" in result.stderr and "give a name" in result.stderr
    assert "Traceback" not in result.stderr


def test_the_package_metadata_uses_no_deprecated_form():
    """``project.license`` is an SPDX expression (a TOML table is deprecated by setuptools,
    which warns on every ``pip install`` and stops accepting it in February 2027), with a
    build backend recent enough to read it."""
    import tomllib

    meta = tomllib.loads((ROOT / "pyproject.toml").read_text())
    assert meta["project"]["license"] == "MIT"
    assert "setuptools>=77" in meta["build-system"]["requires"]


def test_a_weights_csv_without_its_header_reads_every_row(tmp_path, jpeg_bracket):
    """``merge --lut``: a headerless CSV is read from its first row (it lost one row, then
    was refused as 255 rows for 256 code values); a table without its z column, or with
    too few columns, is refused for that fault."""
    from click.testing import CliRunner

    from conftest import frames_of
    from hdrmerge_cli.cli import cli

    folder, meta = jpeg_bracket
    frames = [str(p) for p in frames_of(folder, meta)]
    run = lambda *a: CliRunner().invoke(cli, [str(x) for x in a])
    assert run("weights-lut", *frames, "-o", tmp_path / "w.csv").exit_code == 0
    lines = (tmp_path / "w.csv").read_text().splitlines()
    (tmp_path / "plain.csv").write_text("\n".join(lines[1:]) + "\n")
    (tmp_path / "no_z.csv").write_text("\n".join(",".join(ln.split(",")[1:]) for ln in lines[1:]) + "\n")
    (tmp_path / "two.csv").write_text("\n".join(",".join(ln.split(",")[:2]) for ln in lines) + "\n")
    with_header = run("merge", *frames, "--lut", tmp_path / "w.csv", "-o", tmp_path / "a.exr")
    without = run("merge", *frames, "--lut", tmp_path / "plain.csv", "-o", tmp_path / "b.exr")
    assert with_header.exit_code == 0 and without.exit_code == 0, without.output
    from hdrmerge_cli.io.images import read_exr

    assert (read_exr(str(tmp_path / "a.exr"))[0] == read_exr(str(tmp_path / "b.exr"))[0]).all()
    no_z = run("merge", *frames, "--lut", tmp_path / "no_z.csv", "-o", tmp_path / "c.exr")
    assert no_z.exit_code == 1 and "the first column must be the code value z" in no_z.stderr
    two = run("merge", *frames, "--lut", tmp_path / "two.csv", "-o", tmp_path / "d.exr")
    assert two.exit_code == 1 and "columns do not fit" in two.stderr and "rows" not in two.stderr


def test_estimate_crf_takes_repeated_exposures_as_more_data(tmp_path, jpeg_bracket):
    """Two frames of one exposure (an ISO change inside a real bracket makes them) are more
    data for the response, not an error; frames labelled alike that read differently are
    refused, naming both and the exposure times."""
    from click.testing import CliRunner

    from conftest import frames_of
    from hdrmerge_cli.cli import cli

    folder, meta = jpeg_bracket
    frames = [str(p) for p in frames_of(folder, meta)]
    shutil.copy(frames[1], tmp_path / "repeat.jpg")
    run = lambda *a: CliRunner().invoke(cli, [str(x) for x in a])
    ok = run("estimate-crf", *frames, tmp_path / "repeat.jpg", "-o", tmp_path / "r.json")
    assert ok.exit_code == 0, ok.output
    bad = run("estimate-crf", *frames, "-o", tmp_path / "b.json", "--times", "0.01,0.01,0.02")
    assert bad.exit_code == 1 and "labelled the same exposure" in bad.stderr
    assert "check the exposure times" in bad.stderr and not (tmp_path / "b.json").exists()


def test_a_bracket_transparent_everywhere_is_refused_as_transparent(run, tmp_path):
    """Three RGBA PNGs with alpha 0 everywhere: no frame measures any light, so nothing is
    written and the one line says transparent (not 'reads black', not a bound the EXR would
    not hold); frames transparent only in part still merge."""
    import numpy as np
    import OpenImageIO as oiio

    rng = np.random.default_rng(0)
    paths = {"all": [], "part": []}
    for k in range(3):
        rgb = rng.integers(20, 230, (48, 64, 3), dtype=np.uint8)
        for name, opaque in (("all", 0), ("part", 32)):
            alpha = np.zeros((48, 64, 1), np.uint8)
            alpha[:, opaque:] = 255 if opaque else 0
            spec = oiio.ImageSpec(64, 48, 4, oiio.UINT8)
            spec.alpha_channel = 3
            path = str(tmp_path / f"{name}{k}.png")
            out = oiio.ImageOutput.create(path)
            assert out.open(path, spec) and out.write_image(np.ascontiguousarray(np.concatenate([rgb, alpha], -1)))
            out.close()
            paths[name].append(path)
    args = ("--crf", "srgb", "--times", "0.01,0.04,0.16", "--align", "off")
    proc = run("merge", *paths["all"], *args, "-o", tmp_path / "all.exr", check=False)
    assert proc.returncode == 1 and "Traceback" not in proc.stderr, proc.stderr
    assert proc.stderr.strip().splitlines() == [
        f"hdrmerge-cli: error: {paths['all'][0]} ... all2.png: every pixel is transparent (alpha 0) in every frame, so "
        "no frame measures any light and there is nothing to merge"]
    assert not (tmp_path / "all.exr").exists() and not (tmp_path / "all.profile.json").exists()
    run("merge", *paths["part"], *args, "-o", tmp_path / "part.exr")
    assert (tmp_path / "part.exr").exists()
