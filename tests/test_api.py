"""The Python API (hdrmerge_cli.merge / merge_arrays): the README's example runs, arrays
merge like the files they came from, and the variance channel agrees with Monte-Carlo."""
from __future__ import annotations

import json
import re
from pathlib import Path

import numpy as np
import pytest

import hdrmerge_cli
from conftest import frames_of
from hdrmerge_cli.core.errors import HdrMergeError
from hdrmerge_cli.io.frames import load_codes, read_frame

README = Path(__file__).resolve().parents[1] / "README.md"


def test_readme_api_example_runs(tmp_path, run, monkeypatch):
    """The README's Python example, as written, on a simulated bracket in its folder."""
    block = re.search(r"\*\*Python API\*\*.*?```python\n(.*?)```", README.read_text(), re.S).group(1)
    run("simulate", "-o", tmp_path / "bracket", "--size", "160x120", "--frames", "3", "-q")
    monkeypatch.chdir(tmp_path)
    monkeypatch.setenv("HDRMERGE_CLI_CACHE_DIR", str(tmp_path / "cache"))
    scope: dict = {}
    exec(compile(block, "README.md", "exec"), scope)
    assert scope["rgb"].shape == (120, 160, 3) and scope["rgb"].dtype == np.float32
    assert scope["sd"].shape == (120, 160, 3) and np.all(np.isfinite(scope["sd"]))
    assert scope["flags"].shape == (120, 160)
    assert (tmp_path / "merged.exr").exists() and (tmp_path / "merged.profile.json").exists()
    assert scope["hdr"].shape == (64, 96, 3) and np.all(np.isfinite(scope["hdr"]))


def test_api_is_lazy_and_exported():
    assert {"merge", "merge_arrays", "Merged", "MergeOptions"} <= set(hdrmerge_cli.__all__)
    with pytest.raises(AttributeError):
        hdrmerge_cli.no_such_name  # noqa: B018


def test_version_lives_in_a_leaf_module():
    """No module imports ``__version__`` from the package root (whose lazy API import would
    close a cycle through ``hdrmerge_cli/__init__.py``): all take it from ``_version``."""
    from hdrmerge_cli._version import __version__

    assert hdrmerge_cli.__version__ == __version__
    package = Path(hdrmerge_cli.__file__).parent
    offenders = [str(p.relative_to(package)) for p in package.rglob("*.py")
                 if "from hdrmerge_cli import __version__" in p.read_text()]
    assert not offenders


def test_merge_arrays_equals_the_files(jpeg_bracket, dng_bracket):
    """Decoded frames give the merge of their files: images exactly, RAW mosaics to float
    rounding (the simulator's camera: white balance 1, identity matrix)."""
    folder, meta = jpeg_bracket
    paths = frames_of(folder, meta)
    codes = [load_codes(read_frame(str(p))) for p in paths]
    a = hdrmerge_cli.merge_arrays(codes[::-1], meta["exposure_times"][::-1], crf="srgb")  # any order
    b = hdrmerge_cli.merge(paths, crf="srgb")
    np.testing.assert_array_equal(a.image, b.image)
    folder, meta = dng_bracket
    paths = frames_of(folder, meta)
    frame = read_frame(str(paths[0]))
    mosaics = [load_codes(read_frame(str(p))) for p in paths]
    noise = "sigma_o2=9,alpha=0.25,beta=0"
    a = hdrmerge_cli.merge_arrays(mosaics, meta["exposure_times"], cfa_pattern=meta["cfa_pattern"],
                                  black=float(frame.black[0]), white=float(frame.white[0]), noise=noise)
    b = hdrmerge_cli.merge(paths, noise=noise)
    np.testing.assert_allclose(a.image, b.image, rtol=1e-4, atol=1e-6 * float(b.image.max()))


def test_time_options_take_numbers(jpeg_bracket):
    """``reference`` and ``times`` take seconds as numbers as well as text; bad values are
    an HdrMergeError naming the option, raised before any frame is read."""
    folder, meta = jpeg_bracket
    paths = frames_of(folder, meta)
    a = hdrmerge_cli.merge(paths, crf="srgb", reference=0.01, times=meta["exposure_times"])
    b = hdrmerge_cli.merge(paths, crf="srgb", reference="1/100",
                           times=",".join(repr(t) for t in meta["exposure_times"]))
    assert a.h_ref == b.h_ref == 0.01
    np.testing.assert_array_equal(a.image, b.image)
    for kw, what in [({"reference": -1.0}, "--reference"), ({"reference": float("nan")}, "--reference"),
                     ({"reference": "soon"}, "--reference"), ({"times": [0.01, None, 1]}, "times")]:
        with pytest.raises(HdrMergeError, match=what):
            hdrmerge_cli.merge(["/no/such/frame.jpg"], **kw)


def test_merge_arrays_refuses_bad_input():
    ok = np.zeros((8, 8, 3), np.uint8)
    for codes, times, kw, what in [
        ([ok, ok], [1.0], {}, "exposure times"),
        ([ok, np.zeros((8, 9, 3), np.uint8)], [1.0, 2.0], {}, "differs"),
        ([ok.astype(np.float32)] * 2, [1.0, 2.0], {}, "uint8 or uint16"),
        ([ok, ok], [1.0, -2.0], {}, "positive"),
        ([np.zeros((8, 8), np.uint16)] * 2, [1.0, 2.0], {"cfa_pattern": "XYZW"}, "pattern"),
    ]:
        with pytest.raises(HdrMergeError, match=what):
            hdrmerge_cli.merge_arrays(codes, times, **kw)


def test_variance_channel_agrees_with_monte_carlo():
    """``extra_channels=("variance",)`` through the whole merge (the RAW defaults: ML and
    one IRLS pass; --cfa, so no colour transform): over 400 simulated 12-bit brackets of a
    ramp, the mean predicted variance matches the empirical one within 10 % in every
    2-stop band that some frame measures unclipped."""
    rng = np.random.default_rng(20)
    sigma_o2, alpha = 4.0, 0.5  # (17): y = sqrt(alpha) x + read noise, x ~ Poisson(t E) electrons
    times = [1.0, 4.0, 16.0]
    black, white = 64.0, 4095.0
    e = np.geomspace(2.0, 3000.0, 96)  # code values per second above black
    h, w = 16, 96
    electrons = np.broadcast_to(e / np.sqrt(alpha), (h, w))
    outs, preds = [], []
    for _ in range(400):
        codes = []
        for t in times:
            y = np.sqrt(alpha) * rng.poisson(electrons * t) + rng.standard_normal((h, w)) * np.sqrt(sigma_o2)
            codes.append(np.clip(np.round(y + black), 0, white).astype(np.uint16))
        m = hdrmerge_cli.merge_arrays(codes, times, cfa_pattern="RGGB", black=black, white=white, bits=12,
                                      cfa=True, extra_channels=("variance",), reference="1",
                                      noise="sigma_o2=4,alpha=0.5,beta=0")
        outs.append(m.image[..., 0])
        preds.append(m.variance[..., 0])
    outs, preds = np.array(outs), np.array(preds)
    empirical = outs.var(axis=0).mean(axis=0)
    predicted = preds.mean(axis=(0, 1))
    measured = e * times[0] < (white - black) * 0.9  # the shortest frame is unclipped
    bands = np.floor(np.log2(e / e[0]) / 2)
    for band in np.unique(bands[measured]):
        sel = measured & (bands == band)
        ratio = predicted[sel].sum() / empirical[sel].sum()
        assert 0.9 < ratio < 1.1, (band, ratio)


def test_json_summary_matches_cli(tmp_path, run, dng_bracket):
    folder, meta = dng_bracket
    paths = frames_of(folder, meta)
    proc = run("merge", *paths, "-o", tmp_path / "m.exr", "--json", "-q", "--noise", "sigma_o2=9,alpha=0.25,beta=0")
    cli = json.loads(proc.stdout)
    api = hdrmerge_cli.merge(paths, noise="sigma_o2=9,alpha=0.25,beta=0").summary()
    for key in ("weights", "estimator", "variance", "irls_iterations", "reference_exposure", "channels"):
        assert api[key] == cli[key], key
