"""hdrmerge-cli info and core/coverage.py."""
import json

import numpy as np
import pytest

from conftest import SHARED, frames_of, needs_shared
from hdrmerge_cli.core.coverage import Coverage, clip_classes


def test_clip_classes_use_each_channels_levels():
    """A 2 x 2 CFA cell with per-channel black/white, against a per-sample loop."""
    rng = np.random.default_rng(2)
    codes = rng.integers(0, 1100, (6, 8)).astype(np.uint16)
    pattern = np.array([[0, 1], [3, 2]])
    black, white = np.array([60.0, 64.0, 70.0, 66.0]), np.array([1000.0, 1010.0, 1020.0, 1030.0])
    clipped, dark = clip_classes(codes, pattern, black, white)
    for y in range(6):
        for x in range(8):
            c = pattern[y % 2, x % 2]
            assert clipped[y, x] == (codes[y, x] >= white[c]) and dark[y, x] == (codes[y, x] <= black[c])


def test_clip_classes_interleaved_rgb():
    codes = np.array([[[0, 255, 7], [255, 3, 0]]], np.uint8)
    clipped, dark = clip_classes(codes, np.array([[0, 1, 2]]), np.zeros(3), np.full(3, 255.0))
    assert clipped.tolist() == [[[False, True, False], [True, False, False]]]
    assert dark.tolist() == [[[True, False, False], [False, False, True]]]


def test_coverage_splits_unmeasured_pixels_by_what_is_missing():
    """Four samples: measured once; clipped everywhere; dark everywhere; dark in the short
    frame and clipped in the long one (a gap)."""
    cov = Coverage()
    short = np.array([0, 255, 0, 0])
    long = np.array([100, 255, 0, 255])
    for z in (short, long):
        cov.add(z >= 255, z <= 0)
    assert (cov.uncovered, cov.too_bright, cov.too_dark, cov.gap) == (0.75, 0.25, 0.25, 0.25)


def test_info_reports_frames_and_coverage(run, dng_bracket):
    folder, meta = dng_bracket
    paths = frames_of(folder, meta)
    report = json.loads(run("info", *reversed(paths), "--json").stdout)
    times = [f["exposure_time"] for f in report["frames"]]
    assert times == sorted(times) and len(times) == 5  # shortest first, whatever the argument order
    first = report["frames"][0]
    assert first["bits"] == 14 and first["black"][0] == 512 and first["white"][0] == 16383
    assert 0 <= first["clipped_fraction"] < report["frames"][-1]["clipped_fraction"] <= 1
    assert report["frames"][0]["dark_fraction"] >= report["frames"][-1]["dark_fraction"]
    assert report["bracket"]["covers_scene"] is (report["bracket"]["uncovered_fraction"] <= 1e-3)

    # without the shortest frames the bright parts are clipped everywhere: the advice says what to add
    partial = json.loads(run("info", *paths[-1:], "--json").stdout)["bracket"]
    assert partial["covers_scene"] is False and partial["too_bright_fraction"] > 0
    assert "shorter than" in partial["advice"]
    table = run("info", *paths).stdout
    assert table.splitlines()[0].split()[:3] == ["file", "camera", "exposure"]
    assert "bracket: 5 frames" in table


def test_info_on_a_bad_file_is_one_line(run, tmp_path):
    bad = tmp_path / "broken.jpg"
    bad.write_bytes(b"not a jpeg")
    proc = run("info", bad, check=False)
    assert proc.returncode == 1 and "broken.jpg" in proc.stderr and len(proc.stderr.strip().splitlines()) == 1


@pytest.mark.parametrize("args", [[], ["--json"]])
def test_info_needs_images(run, args):
    proc = run("info", *args, check=False)
    assert proc.returncode == 2


@needs_shared
def test_a_few_pixels_unmeasured_are_reported_without_the_verdict():
    """office_jpg leaves about ten of 540,000 pixels dark in every frame: the bracket covers
    its scene (within the 0.1 % tolerated), and the share is still reported."""
    from hdrmerge_cli.pipeline.info import UNCOVERED_TOLERATED, bracket_info

    report = bracket_info(sorted(str(p) for p in (SHARED / "brackets" / "office_jpg").glob("*.jpg")))["bracket"]
    assert 0 < report["uncovered_fraction"] < UNCOVERED_TOLERATED
    assert report["covers_scene"] is True
    assert "dark in every frame" in report["advice"] and "0.1 % of pixels tolerated" in report["advice"]
