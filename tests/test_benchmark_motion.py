"""Smoke test of the motion benchmark (benchmarks/motion.py): its smallest configuration, one
random RAW case of 200 x 150 px, no peers and no real brackets, runs end to end and its table
has numbers.  Nothing about the alignment's quality is asserted (the benchmark measures it)."""
import re

import pytest

from benchmarks import motion

needs_hdr = pytest.mark.skipif(not (motion.DATA / "hdr").is_dir(), reason=f"{motion.DATA / 'hdr'} is missing")


@needs_hdr
def test_smallest_configuration_fills_the_table(tmp_path):
    out = tmp_path / "motion.md"
    text = motion.main(quick=True, cases=1, size=(200, 150), real=False, peers=False, out=out)
    assert out.read_text() == text
    assert "## Against the targets" in text and "every case failed" not in text
    rows = [ln for ln in text.splitlines() if ln.startswith("| 0 | raw |")]
    assert len(rows) == 1 and "failed" not in rows[0]
    cells = [c.strip() for c in rows[0].strip("|").split("|")]
    # PSNR static / auto / similarity: three finite numbers; times and peak RSS measured
    assert len(re.findall(r"-?\d+\.\d+", cells[11])) == 3
    assert all(re.fullmatch(r"\d+(\.\d+)? / \d+(\.\d+)?", cells[k]) for k in (15, 16))
    target_rows = [ln for ln in text.splitlines() if ln.startswith("| shift (centre)")]
    assert target_rows and re.search(r"\d+ % \(\d/1\)", target_rows[0])


def test_true_warp_inverts_the_rendering_map():
    """The warp scored against (reference -> frame) is the inverse of the frame's sampling map
    composed with the reference's."""
    import numpy as np

    case = motion.draw_case(3, 400, 300, ["x"])
    for k in range(case.n):
        w, s = case.true_warp(k), case.sample_map(k)
        r = np.array([123.0, 45.0])
        p = w[:, :2] @ r + w[:, 2]  # reference pixel -> frame pixel
        np.testing.assert_allclose(s[:, :2] @ p + s[:, 2], r + motion.PAD, atol=1e-9)  # both see this scene point
