"""The Python API (hdrmerge_cli.merge, estimate_response, estimate_noise, register,
ghost_mask on arrays; merge_files on files): each against an independent computation on
seeded synthetic stacks, the docstrings' examples run, the arrays merge like the files
they came from, bad input is a one-line HdrMergeError, and the options' split."""
from __future__ import annotations

import doctest
import json
import pickle
import re
import subprocess
import sys
from pathlib import Path

import cv2
import numpy as np
import pytest

import hdrmerge_cli
from conftest import frames_of
from hdrmerge_cli import api
from hdrmerge_cli.core.crf import CRF
from hdrmerge_cli.core.errors import HdrMergeError
from hdrmerge_cli.core.noise import NoiseParams
from hdrmerge_cli.io.frames import load_codes, read_frame
from hdrmerge_cli.pipeline import options as options_module
from hdrmerge_cli.pipeline.options import InputOptions, MergeOptions, MergeSettings, OutputOptions

README = Path(__file__).resolve().parents[1] / "README.md"

pytestmark = pytest.mark.filterwarnings("ignore::numpy.exceptions.RankWarning")


# ---------------------------------------------------------------- synthetic stacks
def texture(h: int, w: int, seed: int, mean: float = 0.2, contrast: float = 1.0) -> np.ndarray:
    """A smooth random scene (full scale per second), log-normal about ``mean``."""
    rng = np.random.default_rng(seed)
    return mean * np.exp(contrast * cv2.GaussianBlur(rng.standard_normal((h, w)), (0, 0), 2.0))


def encode(x: np.ndarray, gamma: float = 1.0, bits: int = 8) -> np.ndarray:
    """Noiseless codes of the linear signal ``x`` (1 = clipping) through ``v = x**(1/gamma)``."""
    top = 2**bits - 1
    return np.round(top * np.clip(x, 0, 1) ** (1 / gamma)).astype(np.uint8 if bits == 8 else np.uint16)


# ---------------------------------------------------------------- the package
def test_api_is_lazy_and_exported():
    assert {"merge", "merge_files", "estimate_response", "estimate_noise", "register", "ghost_mask", "Registration",
            "Merged", "MergeSettings", "CRF", "NoiseParams"} <= set(hdrmerge_cli.__all__)
    for name in hdrmerge_cli.__all__:
        assert getattr(hdrmerge_cli, name) is not None
    with pytest.raises(AttributeError):
        hdrmerge_cli.no_such_name  # noqa: B018
    code = ("import sys, hdrmerge_cli, hdrmerge_cli.cli.merge; "
            "print('hdrmerge_cli.api' in sys.modules)")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout
    assert out.strip() == "False"  # the command line does not import the API


def test_version_lives_in_a_leaf_module():
    """No module imports ``__version__`` from the package root (whose lazy API import would
    close a cycle through ``hdrmerge_cli/__init__.py``): all take it from ``_version``."""
    from hdrmerge_cli._version import __version__

    assert hdrmerge_cli.__version__ == __version__
    package = Path(hdrmerge_cli.__file__).parent
    offenders = [str(p.relative_to(package)) for p in package.rglob("*.py")
                 if "from hdrmerge_cli import __version__" in p.read_text()]
    assert not offenders


def test_docstring_examples_run():
    """Every example in the API's and the options' docstrings, as written."""
    for module in (api, options_module):
        result = doctest.testmod(module, optionflags=doctest.ELLIPSIS)
        assert result.failed == 0 and result.attempted > 0, module.__name__
    assert doctest.testmod(api).attempted >= 40  # each public function has a running example


def test_readme_names_exist():
    """Every ``hdrmerge_cli.<name>`` and keyword the README's Python section uses is the
    API's (the section is a sketch on placeholder data; the doctests run the functions)."""
    text = README.read_text()
    section = text[text.index("## Python API"):]
    block = re.search(r"```python\n(.*?)```", section, re.S).group(1)
    names = set(re.findall(r"hdrmerge_cli\.(\w+)", block))
    assert names and names <= set(hdrmerge_cli.__all__), names - set(hdrmerge_cli.__all__)
    for call in re.finditer(r"hdrmerge_cli\.(\w+)\((.*?)\)\s*(?:#|$)", block, re.M):
        fn = getattr(hdrmerge_cli, call.group(1))
        if fn is hdrmerge_cli.merge_files:
            continue  # takes MergeOptions' fields
        for kw in re.findall(r"(\w+)=", call.group(2)):
            assert kw in fn.__code__.co_varnames[:fn.__code__.co_argcount + fn.__code__.co_kwonlyargcount], (fn, kw)


# ---------------------------------------------------------------- merge
@pytest.mark.parametrize("bits", [8, 16])
def test_merge_recovers_a_noiseless_radiance(bits):
    """Noiseless gamma-2.2 (8-bit) or linear (16-bit) frames two stops apart, response
    given: the merge returns the scene (full scale per second, reference 1 s) wherever
    some frame measures it unclipped, within the codes' quantisation (8-bit: half a code
    through the response, at most 1.5 % where the best frame reads 1/4 of full scale or
    more; 16-bit: 0.1 %); the frames' order does not matter."""
    scene = np.geomspace(0.05, 30.0, 64 * 96).reshape(64, 96, 1) * np.array([1.0, 0.7, 0.4])
    times = [1 / 32, 1 / 8, 1 / 2]
    gamma = 2.2 if bits == 8 else 1.0
    stack = [encode(scene * t, gamma, bits) for t in times]
    response = 2.2 if bits == 8 else "linear"
    noise = NoiseParams(sigma_o2=0.25, alpha=1e-3)  # quantisation-level noise: ML weights ~ exposure
    hdr = hdrmerge_cli.merge(stack, times, response=response, noise=noise, align="off")
    assert hdr.shape == (64, 96, 3) and hdr.dtype == np.float32
    measured = (scene * times[-1] < 1) | (scene * times[0] < 0.97)
    best = np.max([np.where(scene * t < 0.97, scene * t, 0) for t in times], axis=0)  # brightest unclipped reading
    ok = measured & (best > 0.25)
    err = np.abs(hdr / scene - 1)
    assert np.max(err[ok]) < (0.015 if bits == 8 else 1e-3)
    shuffled = hdrmerge_cli.merge(stack[::-1], times[::-1], response=response, noise=noise, align="off")
    np.testing.assert_array_equal(shuffled, hdr)


def test_merge_of_grey_frames_and_the_reference():
    """(H, W) frames merge to (H, W); ``reference`` scales the result (1 s: per second)."""
    scene = np.geomspace(0.1, 8.0, 32 * 48).reshape(32, 48)
    times = [1 / 8, 1 / 2]
    stack = [encode(scene * t, 1.0, 16) for t in times]
    kw = dict(response="linear", noise={"sigma_o2": 0.25, "alpha": 1e-3}, align="off")
    per_second = hdrmerge_cli.merge(stack, times, **kw)
    longest = hdrmerge_cli.merge(stack, times, reference="longest", **kw)
    assert per_second.shape == (32, 48)
    np.testing.assert_allclose(longest, per_second * 0.5, rtol=1e-5)


def test_merge_measures_the_response_when_none_is_given():
    """No response: it is measured on the stack (as ``estimate_response``), so a gamma-2.2
    stack merges near the scene although nothing said gamma 2.2."""
    scene = texture(96, 128, 5, mean=0.3, contrast=1.5)
    times = [1 / 8, 1 / 2, 2.0]
    stack = [encode(scene * t, 2.2) for t in times]
    hdr = hdrmerge_cli.merge(stack, times, align="off")
    ok = (scene * times[-1] > 0.05) & (scene * times[0] < 0.9)
    assert np.median(np.abs(hdr[ok] / scene[ok] - 1)) < 0.03


def test_array_merge_equals_the_files(jpeg_bracket, dng_bracket):
    """Decoded frames give the merge of their files: images exactly, RAW mosaics to float
    rounding (the simulator's camera: white balance 1, identity matrix)."""
    folder, meta = jpeg_bracket
    paths = frames_of(folder, meta)
    codes = [load_codes(read_frame(str(p))) for p in paths]
    a = hdrmerge_cli.merge(codes[::-1], meta["exposure_times"][::-1], response="srgb", reference="geomean")
    b = hdrmerge_cli.merge_files(paths, crf="srgb")
    np.testing.assert_array_equal(a, b.image)
    folder, meta = dng_bracket
    paths = frames_of(folder, meta)
    frame = read_frame(str(paths[0]))
    mosaics = [load_codes(read_frame(str(p))) for p in paths]
    a = hdrmerge_cli.merge(mosaics, meta["exposure_times"], cfa=meta["cfa_pattern"], black=float(frame.black[0]),
                           white=float(frame.white[0]), noise=NoiseParams(sigma_o2=9, alpha=0.25),
                           reference="geomean")
    b = hdrmerge_cli.merge_files(paths, noise="sigma_o2=9,alpha=0.25,beta=0")
    np.testing.assert_allclose(a, b.image, rtol=1e-4, atol=1e-6 * float(b.image.max()))


def test_variance_agrees_with_monte_carlo():
    """``return_variance`` through the whole merge (the RAW defaults: ML and one IRLS
    pass; ``demosaic=False``, so no colour transform): over 300 simulated 12-bit brackets
    of a ramp, the mean predicted variance matches the empirical one within 10 % in every
    2-stop band that some frame measures unclipped."""
    rng = np.random.default_rng(20)
    sigma_o2, alpha = 4.0, 0.5  # (17): y = sqrt(alpha) x + read noise, x ~ Poisson(t E) electrons
    times = [1.0, 4.0, 16.0]
    black, white = 64.0, 4095.0
    e = np.geomspace(2.0, 3000.0, 96)  # code values per second above black
    h, w = 16, 96
    electrons = np.broadcast_to(e / np.sqrt(alpha), (h, w))
    outs, preds = [], []
    for _ in range(300):
        codes = []
        for t in times:
            y = np.sqrt(alpha) * rng.poisson(electrons * t) + rng.standard_normal((h, w)) * np.sqrt(sigma_o2)
            codes.append(np.clip(np.round(y + black), 0, white).astype(np.uint16))
        m, v = hdrmerge_cli.merge(codes, times, cfa="RGGB", black=black, white=white, bits=12, demosaic=False,
                                  noise=NoiseParams(sigma_o2, alpha), align="off", return_variance=True)
        assert m.shape == v.shape == (h, w)
        outs.append(m)
        preds.append(v)
    outs, preds = np.array(outs), np.array(preds)
    empirical = outs.var(axis=0).mean(axis=0)
    predicted = preds.mean(axis=(0, 1))
    measured = e * times[0] < (white - black) * 0.9  # the shortest frame is unclipped
    bands = np.floor(np.log2(e / e[0]) / 2)
    for band in np.unique(bands[measured]):
        sel = measured & (bands == band)
        ratio = predicted[sel].sum() / empirical[sel].sum()
        assert 0.9 < ratio < 1.1, (band, ratio)


# ---------------------------------------------------------------- estimate_response
def test_estimate_response_recovers_a_gamma():
    """A gamma-2.2 8-bit stack (noiseless, a textured scene): the measured inverse response
    is within 0.02 of ``v**2.2`` over the codes the frames hold, and merges like the truth."""
    scene = texture(128, 160, 7, mean=0.3, contrast=1.5)
    times = [1 / 16, 1 / 4, 1.0, 4.0]
    stack = [encode(scene * t, 2.2) for t in times]
    crf = hdrmerge_cli.estimate_response(stack, times)
    assert isinstance(crf, CRF) and crf.table.shape[1] == 256 and not crf.is_linear
    v = np.arange(16, 240) / 255
    for c in range(crf.table.shape[0]):
        assert np.max(np.abs(crf.inverse(v, c) - v**2.2)) < 0.02
    np.testing.assert_allclose(crf.inverse(np.array([0.0, 1.0]), 0), [0.0, 1.0], atol=1e-3)
    a = hdrmerge_cli.merge(stack, times, response=crf, align="off")
    b = hdrmerge_cli.merge(stack, times, response=2.2, align="off")
    ok = (b > 0.05) & (b < 5)
    assert np.median(np.abs(a[ok] / b[ok] - 1)) < 0.02


def test_estimate_response_refuses_what_cannot_pin_it():
    scene = texture(64, 64, 1)
    one = encode(scene, 2.2)
    with pytest.raises(HdrMergeError, match="two exposures"):
        hdrmerge_cli.estimate_response([one, one], [0.5, 0.5])
    # frames whose brightness contradicts their times
    with pytest.raises(HdrMergeError):
        hdrmerge_cli.estimate_response([encode(scene * 4, 2.2), encode(scene, 2.2)], [0.5, 2.0])


# ---------------------------------------------------------------- estimate_noise
def test_estimate_noise_recovers_simulated_parameters():
    """12-bit mosaics of flat patches simulated under (17) with sigma_o2 = 9, alpha = 0.25
    (0.5 code values per electron): every channel within 15 % (alpha) and 30 % (sigma_o2),
    beta reported 0; the result feeds the merge."""
    rng = np.random.default_rng(11)
    sigma_o2, alpha = 9.0, 0.25
    scene = np.kron(np.geomspace(20, 3500, 48).reshape(6, 8), np.ones((32, 24)))  # code values per second
    times = [0.25, 1.0, 4.0]
    stack = [np.clip(np.round(np.sqrt(alpha) * rng.poisson(scene * t / np.sqrt(alpha))
                              + rng.normal(0, np.sqrt(sigma_o2), scene.shape) + 64), 0, 4095).astype(np.uint16)
             for t in times]
    noise = hdrmerge_cli.estimate_noise(stack, times, cfa="GRBG", black=64, white=4095, bits=12)
    assert sorted(noise) == ["B", "G", "G2", "R"]
    for ch, p in noise.items():
        assert isinstance(p, NoiseParams) and p.beta == 0
        assert abs(p.alpha / alpha - 1) < 0.15, (ch, p)
        assert abs(p.sigma_o2 / sigma_o2 - 1) < 0.3, (ch, p)
    hdr = hdrmerge_cli.merge(stack, times, cfa="GRBG", black=64, white=4095, bits=12, noise=noise, demosaic=False,
                             align="off", reference=1.0)
    inside = scene[8:-8, 8:-8] < 3500  # away from patch edges, unclipped in the shortest frame
    assert np.median(np.abs(hdr[8:-8, 8:-8][inside] * 4031 / scene[8:-8, 8:-8][inside] - 1)) < 0.02


def test_estimate_noise_of_images_is_on_the_linearised_signal():
    """A linear 16-bit RGB stack of flat patches, one code value per electron and read
    noise 4 (sigma_o2 = 16): per colour channel, alpha within 15 %, sigma_o2 within 30 %."""
    rng = np.random.default_rng(12)
    scene = np.kron(np.geomspace(20, 40000, 32).reshape(4, 8), np.ones((24, 16)))[..., None] * [1.0, 0.8, 0.6]
    times = [0.5, 1.0]
    stack = [np.clip(np.round(rng.poisson(scene * t) + rng.normal(0, 4, scene.shape)), 0, 65535).astype(np.uint16)
             for t in times]
    noise = hdrmerge_cli.estimate_noise(stack, times, response="linear")
    assert sorted(noise) == ["B", "G", "R"]
    for p in noise.values():
        assert abs(p.alpha - 1) < 0.15 and abs(p.sigma_o2 / 16 - 1) < 0.3, p


# ---------------------------------------------------------------- register
def test_register_finds_a_known_shift():
    """Frames of a textured scene shifted by whole pixels (the reference, the middle
    exposure, unmoved): each warp reads its frame at the reference's pixel plus the shift
    the content moved by, within 0.1 px, in the order the frames were given; a static twin
    registers to the identity and is not applied."""
    scene = texture(160, 200, 3, mean=0.25, contrast=1.2)
    times = [1 / 2, 1.0, 2.0]
    shifts = [(3, -2), (0, 0), (-4, 5)]  # (dy, dx) by which each frame's content moved
    frames = [np.roll(scene, s, axis=(0, 1)) * t for s, t in zip(shifts, times)]
    stack = [encode(f, 2.2) for f in frames]
    reg = hdrmerge_cli.register(stack[::-1], times[::-1], response=2.2, motion="translation")
    assert reg.warps.shape == (3, 2, 3) and reg.warps.dtype == np.float64
    assert reg.reference == 1 and reg.applied
    for k, (dy, dx) in zip(range(3), shifts[::-1]):
        np.testing.assert_allclose(reg.warps[k][:, :2], np.eye(2), atol=1e-6)
        np.testing.assert_allclose(reg.warps[k][:, 2], [dx, dy], atol=0.1)
    assert reg.confidence.shape == (3,) and reg.confidence[1] == 1.0
    static = hdrmerge_cli.register([encode(scene * t, 2.2) for t in times], times, response=2.2)
    assert not static.applied
    np.testing.assert_allclose(static.warps[:, :, 2], 0, atol=0.1)


# ---------------------------------------------------------------- ghost_mask
def test_ghost_mask_flags_an_inserted_object_and_nothing_on_a_static_twin():
    rng = np.random.default_rng(4)
    scene = texture(128, 160, 9, mean=0.3, contrast=0.5)
    times = [0.25, 0.5, 1.0]

    def stack(moving: bool):
        out = []
        for k, t in enumerate(times):
            x = scene * t
            if moving and k == 0:
                x = x.copy()
                x[40:80, 60:110] = 0.9  # a bright object in the shortest frame only
            out.append(np.clip(np.round(4000 * x + rng.normal(0, 2, x.shape)), 0, 4095).astype(np.uint16))
        return out

    masks = hdrmerge_cli.ghost_mask(stack(True), times, response="linear", bits=12)
    assert masks.shape == (3, 128, 160) and masks.dtype == np.float32
    assert masks.min() >= 0 and masks.max() <= 1
    assert np.all(masks[0, 45:75, 65:105] > 0.99)  # the object dropped
    assert masks[1].max() == 0  # the reference
    far = np.ones((128, 160), bool)
    far[16:104, 36:134] = False  # beyond the object's blocks and their feathering
    assert masks[0][far].max() == 0 and masks[2].max() == 0
    still = hdrmerge_cli.ghost_mask(stack(False), times, response="linear", bits=12)
    assert still.max() == 0
    assert hdrmerge_cli.ghost_mask(stack(False), times, response="linear", bits=12, mode="auto").max() == 0


# ---------------------------------------------------------------- bad input
def test_bad_input_is_a_one_line_error():
    ok = np.zeros((8, 8, 3), np.uint8)
    mosaic = np.zeros((8, 8), np.uint16)
    cases = [
        (hdrmerge_cli.merge, ([ok, ok], [1.0]), {}, "exposure times"),
        (hdrmerge_cli.merge, ([ok, np.zeros((8, 9, 3), np.uint8)], [1.0, 2.0]), {}, "differs"),
        (hdrmerge_cli.merge, ([ok.astype(np.float32)] * 2, [1.0, 2.0]), {}, "uint8 or uint16"),
        (hdrmerge_cli.merge, ([ok, ok], [1.0, -2.0]), {}, "positive"),
        (hdrmerge_cli.merge, ([ok, ok], [1.0, "soon"]), {}, "times"),
        (hdrmerge_cli.merge, ([], []), {}, "no input"),
        (hdrmerge_cli.merge, ([mosaic] * 2, [1.0, 2.0]), {"cfa": "XYZW"}, "pattern"),
        (hdrmerge_cli.merge, ([mosaic] * 2, [1.0, 2.0]), {"cfa": "RGGB", "response": 2.2}, "linear"),
        (hdrmerge_cli.merge, ([ok, ok], [1.0, 2.0]), {"response": "gamma:2.2"}, "response"),
        (hdrmerge_cli.merge, ([ok, ok], [1.0, 2.0]), {"response": 20.0}, "gamma"),
        (hdrmerge_cli.merge, ([ok, ok], [1.0, 2.0]), {"response": np.linspace(0, 1, 10)}, "entries"),
        (hdrmerge_cli.merge, ([ok, ok], [1.0, 2.0]), {"noise": "sigma_o2=4,alpha=1"}, "noise"),
        (hdrmerge_cli.merge, ([ok, ok], [1.0, 2.0]), {"noise": {"sigma_o2": 4, "alpha": -1}}, "noise"),
        (hdrmerge_cli.merge, ([ok, ok], [1.0, 2.0]), {"weighting": "nope"}, "weighting"),
        (hdrmerge_cli.merge, ([ok, ok], [1.0, 2.0]), {"estimator": "median"}, "estimator"),
        (hdrmerge_cli.merge, ([ok, ok], [1.0, 2.0]), {"align": "yes"}, "align"),
        (hdrmerge_cli.merge, ([ok, ok], [1.0, 2.0]), {"irls": -1}, "irls"),
        (hdrmerge_cli.merge, ([ok, ok], [1.0, 2.0]), {"reference": "soon"}, "reference"),
        (hdrmerge_cli.merge, ([ok, ok], [1.0, 2.0]), {"white": 0.0}, "white"),
        (hdrmerge_cli.merge, (["a.jpg", "b.jpg"], [1.0, 2.0]), {}, "merge_files"),
        (hdrmerge_cli.register, ([ok, ok], [1.0, 2.0]), {"motion": "off"}, "motion"),
        (hdrmerge_cli.ghost_mask, ([ok, ok], [1.0, 2.0]), {"mode": "off"}, "mode"),
    ]
    for fn, args, kw, what in cases:
        with pytest.raises(HdrMergeError, match=what) as exc:
            fn(*args, **kw)
        assert "\n" not in str(exc.value), (what, str(exc.value))


# ---------------------------------------------------------------- files
def test_merge_files_time_options_take_numbers(jpeg_bracket):
    """``reference`` and ``times`` take seconds as numbers as well as text; bad values are
    an HdrMergeError naming the option, raised before any frame is read."""
    folder, meta = jpeg_bracket
    paths = frames_of(folder, meta)
    a = hdrmerge_cli.merge_files(paths, crf="srgb", reference=0.01, times=meta["exposure_times"])
    b = hdrmerge_cli.merge_files(paths, crf="srgb", reference="1/100",
                                 times=",".join(repr(t) for t in meta["exposure_times"]))
    assert a.h_ref == b.h_ref == 0.01
    np.testing.assert_array_equal(a.image, b.image)
    for kw, what in [({"reference": -1.0}, "--reference"), ({"reference": float("nan")}, "--reference"),
                     ({"reference": "soon"}, "--reference"), ({"times": [0.01, None, 1]}, "times"),
                     ({"no_such_option": 1}, "no_such_option")]:
        with pytest.raises(HdrMergeError, match=what):
            hdrmerge_cli.merge_files(["/no/such/frame.jpg"], **kw)


def test_merge_files_takes_objects_as_well_as_text(jpeg_bracket, dng_bracket):
    """``crf`` a CRF and ``noise`` NoiseParams (what the estimators return) merge as their
    text does."""
    folder, meta = jpeg_bracket
    paths = frames_of(folder, meta)
    a = hdrmerge_cli.merge_files(paths, crf=CRF("srgb"))
    b = hdrmerge_cli.merge_files(paths, crf="srgb")
    np.testing.assert_array_equal(a.image, b.image)
    folder, meta = dng_bracket
    paths = frames_of(folder, meta)
    a = hdrmerge_cli.merge_files(paths, noise=NoiseParams(sigma_o2=9, alpha=0.25), align="off")
    b = hdrmerge_cli.merge_files(paths, noise="sigma_o2=9,alpha=0.25,beta=0", align="off")
    np.testing.assert_array_equal(a.image, b.image)
    assert a.summary()["noise"] == b.summary()["noise"]
    with pytest.raises(HdrMergeError, match="noise"):
        hdrmerge_cli.merge_files(paths, noise=[1, 2])


def test_json_summary_matches_cli(tmp_path, run, dng_bracket):
    folder, meta = dng_bracket
    paths = frames_of(folder, meta)
    proc = run("merge", *paths, "-o", tmp_path / "m.exr", "--json", "-q", "--noise", "sigma_o2=9,alpha=0.25,beta=0")
    cli = json.loads(proc.stdout)
    api_summary = hdrmerge_cli.merge_files(paths, noise="sigma_o2=9,alpha=0.25,beta=0").summary()
    for key in ("weights", "estimator", "variance", "irls_iterations", "reference_exposure", "channels"):
        assert api_summary[key] == cli[key], key


# ---------------------------------------------------------------- the options' split
def test_merge_options_compose_algorithm_inputs_and_outputs():
    """Each flat field lands in its part; the algorithm part holds no file concern; the
    composite pickles (batch workers) and copies with changes."""
    opts = MergeOptions.from_fields(output=Path("m.exr"), deghost="on", crf="gamma:2.2", noise_cache=False, irls=0)
    assert opts.algorithm == MergeSettings(deghost="on", irls=0)
    assert opts.inputs == InputOptions(crf="gamma:2.2")
    assert opts.io == OutputOptions(output=Path("m.exr"), noise_cache=False)
    assert opts == MergeOptions(MergeSettings(deghost="on", irls=0), InputOptions(crf="gamma:2.2"),
                                OutputOptions(output=Path("m.exr"), noise_cache=False))
    algorithm_fields = {f for f in MergeSettings.__dataclass_fields__}
    assert not algorithm_fields & {"output", "profile_out", "overwrite", "preview", "compression", "half", "crf",
                                   "noise", "profile", "noise_cache", "extra_channels"}
    assert pickle.loads(pickle.dumps(opts)) == opts
    again = opts.replace(output=Path("n.exr"), align="off")
    assert again.io.output == Path("n.exr") and again.algorithm.align == "off" and opts.io.output == Path("m.exr")
    with pytest.raises(TypeError, match="wrong"):
        MergeOptions.from_fields(wrong=1)
    with pytest.raises(TypeError, match="MergeSettings"):
        MergeOptions(InputOptions())
    with pytest.raises(AttributeError):  # fields are read from their part
        opts.deghost  # noqa: B018


def test_merge_files_refuses_a_response_table_of_another_bit_depth(jpeg_bracket):
    """A CRF object whose table covers 4096 codes, given for 8-bit JPEGs: one error naming
    both sizes, before any merge."""
    from hdrmerge_cli.core.crf import table_crf

    folder, meta = jpeg_bracket
    paths = [str(p) for p in frames_of(folder, meta)]
    crf = table_crf(np.tile(np.linspace(0.0, 1.0, 4096), (3, 1)))
    with pytest.raises(HdrMergeError, match=r"crf: the inverse table has 4096 entries per channel, but .* has 256 "
                                            r"code values"):
        hdrmerge_cli.merge_files(paths, crf=crf, noise_cache=False)
