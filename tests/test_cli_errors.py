"""Bad input: one line naming the file and the problem, exit 1 (data) or 2 (usage),
no traceback, nothing written."""
import os
import shutil

import numpy as np
import pytest

from conftest import frames_of
from hdrmerge_cli.io.images import write_exr, write_ldr


def _fails(run, tmp_path, *args, code=1, expect=()):
    out = tmp_path / "out.exr"
    proc = run("merge", *args, "-o", out, check=False)
    assert proc.returncode == code, proc.stderr
    assert "Traceback" not in proc.stderr
    lines = [ln for ln in proc.stderr.strip().splitlines() if not ln.startswith("hdrmerge-cli: warning")]
    if code == 1:
        assert len(lines) == 1, proc.stderr
    for word in expect:
        assert word in proc.stderr, proc.stderr
    assert not out.exists() and not (tmp_path / "out.profile.json").exists()
    assert not [p for p in tmp_path.iterdir() if ".part" in p.name]
    return proc


def _jpeg(path, value=100, size=(8, 10), **exif):
    write_ldr(str(path), np.full(size + (3,), value, np.uint8), {"ExposureTime": 0.01} | exif)
    return path


def test_missing_file_is_a_usage_error(run, tmp_path):
    _fails(run, tmp_path, tmp_path / "nope.jpg", code=2, expect=["nope.jpg"])


def test_not_an_image(run, tmp_path):
    bad = tmp_path / "text.jpg"
    bad.write_text("hello")
    _fails(run, tmp_path, bad, expect=["text.jpg", "not a readable image"])


def test_truncated_raw(run, tmp_path, dng_bracket):
    folder, meta = dng_bracket
    cut = tmp_path / "cut.dng"
    cut.write_bytes((folder / meta["frames"][0]).read_bytes()[:20000])
    _fails(run, tmp_path, cut, folder / meta["frames"][1], expect=["cut.dng", "RAW"])


def test_truncated_reference_with_motion_options(run, tmp_path):
    """The middle frame's pixels cut off (its header still reads): with --align and
    --deghost its decode fails on the alignment's two threads at once (frames are decoded
    once for the motion passes); still one line naming it, exit 1, nothing written."""
    rng = np.random.default_rng(0)
    paths = []
    for k, t in enumerate((0.01, 0.04, 0.16)):
        p = tmp_path / f"f{k}.jpg"
        write_ldr(str(p), rng.integers(0, 256, (300, 400, 3)).astype(np.uint8), {"ExposureTime": t})
        paths.append(p)
    data = paths[1].read_bytes()
    paths[1].write_bytes(data[: len(data) // 2])
    _fails(run, tmp_path, *paths, "--crf", "srgb", "--align", "auto", "--deghost", "auto", expect=["f1.jpg"])


def test_frames_of_different_sizes(run, tmp_path):
    a = _jpeg(tmp_path / "a.jpg")
    b = _jpeg(tmp_path / "b.jpg", size=(9, 10), ExposureTime=0.1)
    _fails(run, tmp_path, a, b, expect=["b.jpg", "size"])


def test_frames_of_different_cameras(run, tmp_path):
    a = _jpeg(tmp_path / "a.jpg", Make="Canon", Model="A")
    b = _jpeg(tmp_path / "b.jpg", Make="Nikon", Model="B", ExposureTime=0.1)
    _fails(run, tmp_path, a, b, expect=["b.jpg", "Nikon"])


def test_frames_of_different_bit_depths(run, tmp_path):
    a = tmp_path / "a.tif"
    write_ldr(str(a), np.full((8, 10, 3), 100, np.uint8), {"ExposureTime": 0.01})
    b = tmp_path / "b.tif"
    write_ldr(str(b), np.full((8, 10, 3), 100, np.uint16), {"ExposureTime": 0.1})
    _fails(run, tmp_path, a, b, expect=["b.tif", "bit depth"])


def test_missing_exposure_time_suggests_times(run, tmp_path):
    a = tmp_path / "a.png"
    write_ldr(str(a), np.full((8, 10, 3), 100, np.uint8), {})
    _fails(run, tmp_path, a, _jpeg(tmp_path / "b.jpg"), expect=["a.png", "--times"])


def test_equal_exposure_times_are_merged_and_a_disagreement_is_named(run, tmp_path):
    """Two frames of one exposure are a burst: merged, with a warning when their
    content disagrees beyond the noise (here a whole stop brighter: the exposure changed)."""
    a, b = _jpeg(tmp_path / "a.jpg", size=(64, 64)), _jpeg(tmp_path / "b.jpg", value=120, size=(64, 64))
    proc = run("merge", a, b, "-o", tmp_path / "out.exr", "--crf", "srgb", check=False)
    assert proc.returncode == 0 and (tmp_path / "out.exr").exists(), proc.stderr
    assert "b.jpg" in proc.stderr and "warning" in proc.stderr


def test_a_file_given_twice_is_refused_under_any_name(run, tmp_path):
    """The same file twice (a repeated glob, a symbolic link, another relative path) would
    be averaged with itself as if its noise were independent: refused, naming both names,
    before anything is written; estimate-crf refuses it too."""
    a, b = _jpeg(tmp_path / "a.jpg", size=(64, 64)), _jpeg(tmp_path / "b.jpg", value=60, size=(64, 64), ExposureTime=0.005)
    link = tmp_path / "link.jpg"
    link.symlink_to(a)
    for again in (a, link, tmp_path / "." / "a.jpg"):
        proc = _fails(run, tmp_path, a, b, again, expect=[str(again), "given twice"])
        assert str(a) in proc.stderr
    proc = run("estimate-crf", a, b, link, "-o", tmp_path / "crf.json", check=False)
    assert proc.returncode == 1 and "given twice" in proc.stderr and not (tmp_path / "crf.json").exists()
    assert run("merge", a, b, "-o", tmp_path / "out.exr", "--crf", "srgb", check=False).returncode == 0


def test_wrong_number_of_times(run, tmp_path):
    a, b = _jpeg(tmp_path / "a.jpg"), _jpeg(tmp_path / "b.jpg", ExposureTime=0.1)
    _fails(run, tmp_path, a, b, "--times", "1/100", expect=["--times"])


def test_bad_times_value_is_a_usage_error(run, tmp_path):
    a = _jpeg(tmp_path / "a.jpg")
    _fails(run, tmp_path, a, "--times", "fast", code=2, expect=["fast"])


def test_unknown_weighting_is_a_usage_error(run, tmp_path):
    _fails(run, tmp_path, _jpeg(tmp_path / "a.jpg"), "--weights", "magic", code=2)


def test_unknown_crf(run, tmp_path):
    _fails(run, tmp_path, _jpeg(tmp_path / "a.jpg"), "--crf", "banana", expect=["banana"])


def test_one_frame_merges_with_a_warning(run, tmp_path):
    a = _jpeg(tmp_path / "a.jpg")
    proc = run("merge", a, "-o", tmp_path / "one.exr", "--crf", "srgb")
    assert "only one frame" in proc.stderr and (tmp_path / "one.exr").exists()


def test_refuses_to_overwrite_without_flag(run, tmp_path, jpeg_bracket):
    folder, meta = jpeg_bracket
    out = tmp_path / "out.exr"
    out.write_bytes(b"precious")
    proc = run("merge", *frames_of(folder, meta), "-o", out, "--crf", "srgb", check=False)
    assert proc.returncode == 1 and "--overwrite" in proc.stderr and out.read_bytes() == b"precious"
    run("merge", *frames_of(folder, meta), "-o", out, "--crf", "srgb", "--overwrite")
    assert out.read_bytes()[:4] == b"v/1\x01"  # OpenEXR magic


def test_output_folder_missing(run, tmp_path, jpeg_bracket):
    folder, meta = jpeg_bracket
    proc = run("merge", *frames_of(folder, meta), "-o", tmp_path / "no" / "x.exr", check=False)
    assert proc.returncode == 1 and "does not exist" in proc.stderr


@pytest.mark.skipif(os.geteuid() == 0, reason="root reads any file")
def test_unreadable_file(run, tmp_path):
    a = _jpeg(tmp_path / "a.jpg")
    a.chmod(0)
    _fails(run, tmp_path, a, expect=["a.jpg"])


def test_simulate_refuses_to_overwrite(run, tmp_path):
    run("simulate", "-o", tmp_path / "s", "--size", "32x32", "--frames", "2", "-q")
    proc = run("simulate", "-o", tmp_path / "s", "--size", "32x32", "--frames", "2", check=False)
    assert proc.returncode == 1 and "--overwrite" in proc.stderr and "Traceback" not in proc.stderr
    shutil.rmtree(tmp_path / "s")
    proc = run("simulate", "-o", tmp_path / "t", "--size", "16x16", check=False)
    assert proc.returncode == 1 and "32 x 32" in proc.stderr and not list((tmp_path / "t").glob("*.dng"))


def test_messages_say_what_is_wrong(run, tmp_path, dng_bracket, jpeg_bracket):
    """Data errors read 'hdrmerge-cli: error: ...' (like the logs); an EXR among the
    inputs is called an EXR, not a bad RAW; a profile on a RAW bracket does not warn about
    a --crf nobody gave."""
    folder, meta = jpeg_bracket
    frames = frames_of(folder, meta)
    proc = run("merge", folder / "truth.exr", *frames, "--crf", "srgb", "-o", tmp_path / "x.exr", check=False)
    assert proc.returncode == 1 and proc.stderr.startswith("hdrmerge-cli: error: ")
    assert "OpenEXR image" in proc.stderr and "RAW" not in proc.stderr.split("(")[0]
    folder, meta = dng_bracket
    prof = tmp_path / "cam.json"
    run("calibrate-noise", *frames_of(folder, meta), "-o", prof)
    proc = run("merge", *frames_of(folder, meta), "--profile", prof, "-o", tmp_path / "m.exr")
    assert "--crf" not in proc.stderr and "RuntimeWarning" not in proc.stderr


def test_a_file_name_that_is_not_utf8_is_one_line(run, tmp_path, jpeg_bracket):
    folder, meta = jpeg_bracket
    odd = [os.fsdecode(os.fsencode(tmp_path) + b"/fr\xff_%d.jpg" % k) for k in range(3)]
    for src, dst in zip(frames_of(folder, meta), odd):
        shutil.copy(src, dst)
    for args in (["info", *odd], ["merge", *odd, "--crf", "srgb", "-o", tmp_path / "o.exr"]):
        proc = run(*args, check=False)
        assert proc.returncode == 1 and "not valid UTF-8" in proc.stderr and "Traceback" not in proc.stderr
        assert len(proc.stderr.strip().splitlines()) == 1


def test_simulate_from_a_scene_too_dark_leaves_no_folder(run, tmp_path):
    scene = tmp_path / "dim.exr"
    write_exr(str(scene), np.full((64, 64, 3), 1e-6, np.float32), ["R", "G", "B"], {})
    out = tmp_path / "sim"
    proc = run("simulate", "--scene", scene, "-o", out, check=False)
    assert proc.returncode == 1 and "too dark" in proc.stderr and "Traceback" not in proc.stderr
    assert not out.exists()


def test_a_profile_that_is_not_json_is_named_as_the_profile(run, tmp_path, jpeg_bracket):
    """--profile on an EXR: one line naming that file, not an 'unknown CRF' message."""
    folder, meta = jpeg_bracket
    proc = run("merge", *frames_of(folder, meta), "--profile", folder / "truth.exr", "-o", tmp_path / "x.exr",
               check=False)
    assert proc.returncode == 1 and "truth.exr" in proc.stderr and "unknown CRF" not in proc.stderr
    assert len(proc.stderr.strip().splitlines()) == 1 and not (tmp_path / "x.exr").exists()


def test_preview_followed_by_an_option_names_the_mistake(run, tmp_path):
    """`--preview --overwrite`: click takes the option as the preview's path; the error
    says so (usage error, exit 2) instead of complaining about a '.jpg' suffix."""
    a = _jpeg(tmp_path / "a.jpg")
    b = _jpeg(tmp_path / "b.jpg", ExposureTime=0.1)
    proc = _fails(run, tmp_path, a, b, "--preview", "--overwrite", code=2, expect=["--preview", "needs a file name"])
    assert "suffix" not in proc.stderr
