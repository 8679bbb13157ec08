"""The choices (hdrmerge_cli.pipeline.choices): every ``auto`` decided in one module, each as
a Decision that ``merge --json`` and the profile carry."""
import json
import re
from pathlib import Path

import numpy as np
import pytest

from conftest import frames_of
from hdrmerge_cli.pipeline import choices
from hdrmerge_cli.pipeline.choices import AUTO_ALIGN_PX, AUTO_DEGHOST_FRACTION
from hdrmerge_cli.pipeline.records import Decision

PACKAGE = Path(choices.__file__).parents[1]


def test_no_module_but_the_choices_reads_an_auto_setting():
    """``grep`` for a comparison with ``"auto"`` finds it only in choices.py (the command
    line parses the options; ``--compression auto`` is a file format's name, resolved where
    the formats are listed)."""
    readers = set()
    for path in PACKAGE.rglob("*.py"):
        if re.search(r'[!=]= "auto"|"auto" [!=]=', path.read_text()):
            readers.add(path.relative_to(PACKAGE).as_posix())
    assert readers == {"pipeline/choices.py", "io/images.py"}, readers


def _alignment(shifts, raw=False, rotation=0.0, mode="auto"):
    """An Alignment as the registration stage hands it over under ``--align mode`` (not yet
    applied): frames of 40 x 60 with the given (dx, dy) and rotation (radians) against the
    reference (the first)."""
    from hdrmerge_cli.pipeline.records import Alignment

    class F:
        kind = "raw" if raw else "image"
        height, width = 40, 60

    c, s = np.cos(rotation), np.sin(rotation)
    warps = [np.float64([[1, 0, 0], [0, 1, 0]])] + [np.float64([[c, -s, dx], [s, c, dy]]) for dx, dy in shifts]
    frames = [F() for _ in warps]
    motion = choices.registration_plan(mode).motion
    return Alignment(None, motion, "none", "ref", False, frames, warps, [1.0] * len(warps), [], [])


@pytest.mark.parametrize("shift, applied", [(0.2, False), (0.3, True), (5.0, True)])
def test_auto_alignment_applies_the_warps_only_past_the_tolerance(shift, applied):
    out = choices.choose_alignment(_alignment([(shift, 0.0)]), "auto")
    d = out.decision
    assert out.applied == applied == d.value and d.measured
    assert d.statistic == pytest.approx(shift) and d.threshold == AUTO_ALIGN_PX
    assert out.motion == "translation" and out.mode == "auto"  # no rotation found: translation
    assert ("more than" in d.reason) == applied


def test_a_given_alignment_is_applied_and_not_measured():
    out = choices.choose_alignment(_alignment([(0.01, 0.0)], rotation=0.01, mode="similarity"), "similarity")
    assert out.applied and out.motion == "similarity" and not out.decision.measured
    assert out.decision.reason == "--align similarity given"


def test_raw_alignment_moves_whole_cfa_periods_where_they_suffice():
    """A RAW frame 4.1 px off moves by two whole CFA periods (no resampling); 3 px off it is
    resampled colour by colour; 0.1 px off with whole periods nothing moves: not applied."""
    assert choices.choose_alignment(_alignment([(4.1, 0.0)], raw=True), "auto").resampling == "cfa-periods"
    assert choices.choose_alignment(_alignment([(3.0, 0.0)], raw=True), "auto").resampling == "per-colour"
    still = choices.choose_alignment(_alignment([(0.1, 0.0)], raw=True, mode="translation"), "translation")
    assert still.resampling == "cfa-periods" and not still.applied
    assert "whole CFA period" in still.decision.reason


@pytest.mark.parametrize("mode, largest, applied", [("auto", 0.001, False), ("auto", 0.01, True),
                                                    ("on", 0.0, True)])
def test_deghosting_applies_the_masks_on_or_past_the_false_alarms(mode, largest, applied):
    from hdrmerge_cli.pipeline.records import Ghosts

    found = Ghosts(None, False, 1e-3, 4, (40, 60), [largest], [], [], largest=largest)
    out = choices.choose_deghost(found, mode)
    assert out.applied == applied == out.decision.value and out.mode == mode
    assert out.decision.measured == (mode == "auto")
    assert out.decision.threshold == (AUTO_DEGHOST_FRACTION if mode == "auto" else None)


def test_decision_summary_keeps_only_what_was_measured():
    d = Decision("log", True, "why", statistic=1.23456789, uncertainty=float("nan"))
    assert d.summary() == {"value": "log", "measured": True, "reason": "why", "statistic": 1.234568}


def test_merge_json_and_profile_carry_every_decision(run, tmp_path, jpeg_bracket):
    """A default JPEG merge: the alignment, estimator, weights, variance and irls decisions,
    the same in ``--json`` and the profile; the estimator measured on the excess variance
    (its statistic and standard error given), the weights following it; ``--weights``
    given is reported as given."""
    folder, meta = jpeg_bracket
    paths = frames_of(folder, meta)
    out = tmp_path / "m.exr"
    summary = json.loads(run("merge", *paths, "-o", out, "--json", "--no-cache").stdout)
    decisions = summary["decisions"]
    assert set(decisions) == {"align", "estimator", "weights", "variance", "irls"}
    assert all({"value", "measured", "reason"} <= set(d) for d in decisions.values())
    assert decisions["estimator"]["value"] == summary["estimator"]
    assert decisions["weights"]["value"] == summary["weights"]
    assert decisions["align"]["value"] == summary["alignment"]["applied"]
    assert decisions["align"]["threshold"] == AUTO_ALIGN_PX
    est = decisions["estimator"]
    if est["measured"]:
        assert "statistic" in est and "uncertainty" in est
    profile = json.loads((tmp_path / "m.profile.json").read_text())
    assert profile["decisions"] == decisions
    given = json.loads(run("merge", *paths, "-o", tmp_path / "g.exr", "--json", "--no-cache", "--weights", "gaussian",
                           "--align", "off").stdout)["decisions"]
    assert given["weights"] == {"value": "gaussian", "measured": False, "reason": "--weights gaussian given"}
    assert "align" not in given
