"""Speed paths: lazy imports, the fused colour kernel against the reference
colour path, EXR compression, the per-camera noise cache."""
from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from click.testing import CliRunner

# Merges in this session must neither read nor fill the user's noise cache (a measurement
# of an earlier test's bracket would change a later test's result).  Set at collection, so
# it holds for every test module; belongs in conftest.py.

from conftest import frames_of  # noqa: E402
from hdrmerge_cli.cli import COMMANDS, SUMMARIES, cli  # noqa: E402
from hdrmerge_cli.core.cfa import bayer_channels, camera_to_rec709  # noqa: E402
from hdrmerge_cli.core.cfa_to_rgb import raw_to_rgb_rows  # noqa: E402
from hdrmerge_cli.io import noisecache  # noqa: E402
from hdrmerge_cli.io.images import EXR_COMPRESSIONS, exr_compression, read_exr  # noqa: E402
from references import demosaic, raw_to_rgb_rows as raw_to_rgb_rows_reference  # noqa: E402

#: libraries a command must not import unless its path uses them
HEAVY = ("cvxpy", "matplotlib", "scipy.stats", "colour", "colour_demosaicing", "colour_hdri", "cv2")

_PROBE = """
import json, os, sys
from hdrmerge_cli.cli import main
sys.argv = ["hdrmerge-cli"] + json.loads(os.environ["PROBE_ARGS"])
try:
    main()
except SystemExit as exc:
    code = exc.code
else:
    code = 0
with open(os.environ["PROBE_OUT"], "w") as fh:
    json.dump({"code": code, "modules": sorted(sys.modules)}, fh)
"""


@pytest.fixture
def dng_frames(dng_bracket) -> list[str]:
    return [str(p) for p in frames_of(*dng_bracket)]


def _modules_after(args: list[str], tmp_path: Path, env: dict | None = None) -> tuple[int, set[str]]:
    out = tmp_path / "probe.json"
    run_env = os.environ | {"PROBE_ARGS": json.dumps(args), "PROBE_OUT": str(out)} | (env or {})
    subprocess.run([sys.executable, "-c", _PROBE], env=run_env, check=False, capture_output=True, timeout=600)
    data = json.loads(out.read_text())
    return data["code"], set(data["modules"])


def test_import_cli_is_light():
    code = ("import sys, json; import hdrmerge_cli.cli; "
            "print(json.dumps(sorted(sys.modules)))")
    mods = set(json.loads(subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                                         check=True).stdout))
    assert not mods & set(HEAVY + ("numpy", "numba", "scipy", "OpenImageIO", "rawpy")), mods & set(HEAVY)


def test_group_help_imports_no_command(tmp_path):
    code, mods = _modules_after(["--help"], tmp_path)
    assert code == 0
    assert not mods & set(HEAVY + ("numpy", "numba", "scipy")), sorted(mods & set(HEAVY + ("numpy", "numba")))
    assert not any(m.startswith("hdrmerge_cli.pipeline") for m in mods)


@pytest.mark.parametrize("command", ["merge", "info", "simulate"])
def test_command_help_skips_heavy_libraries(tmp_path, command):
    code, mods = _modules_after([command, "--help"], tmp_path)
    assert code == 0
    assert not mods & set(HEAVY), sorted(mods & set(HEAVY))


def test_merge_help_imports_no_numba_scipy_or_the_merge(tmp_path):
    """``merge --help`` reads its choices from the option vocabularies
    (:mod:`hdrmerge_cli.core.choices`, :mod:`hdrmerge_cli.pipeline.options`), not from the
    code behind them: no Numba, SciPy or importlib.metadata (the version is read on
    ``--version`` only), and no merge pipeline."""
    code, mods = _modules_after(["merge", "--help"], tmp_path)
    assert code == 0
    assert not mods & {"numba", "scipy", "importlib.metadata"}, sorted(mods & {"numba", "scipy", "importlib.metadata"})
    assert not mods & {"hdrmerge_cli.pipeline.run", "hdrmerge_cli.pipeline.merge", "hdrmerge_cli.pipeline.batch",
                     "hdrmerge_cli.core.reconstruct"}


def test_kernels_import_numba_on_first_call(tmp_path, dng_frames):
    """core.jit: importing every stage of a merge imports neither Numba nor SciPy, a merge
    refused before any work (an existing output) never imports them, and a kernel's first
    call binds, in its module, the dispatcher ``numba.njit`` makes of the same function
    (its result equal to that of a dispatcher made independently)."""
    code = ("import sys, json; import hdrmerge_cli.pipeline.run, hdrmerge_cli.pipeline.batch, hdrmerge_cli.api; "
            "print(json.dumps(sorted(sys.modules)))")
    mods = set(json.loads(subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                                         check=True).stdout))
    assert not mods & {"numba", "scipy"}, sorted(mods & {"numba", "scipy"})
    (tmp_path / "out.exr").write_bytes(b"keep")
    code, mods = _modules_after(["merge", *dng_frames, "-o", str(tmp_path / "out.exr")], tmp_path)
    assert code == 1 and (tmp_path / "out.exr").read_bytes() == b"keep"
    assert not mods & {"numba", "scipy"}, sorted(mods & {"numba", "scipy"})

    import numba

    from hdrmerge_cli.core import resample

    u = np.linspace(-0.5, 40.0, 64, dtype=np.float32).reshape(8, 8)
    got = resample.spread_code(u)
    assert isinstance(resample._spread_code_rows, numba.core.registry.CPUDispatcher)
    assert resample.prange is numba.prange
    independent = numba.njit(parallel=True, nogil=True)(resample._spread_code_rows.py_func)
    want = np.empty(u.shape, np.uint16)
    independent(u, want, np.float32(1.0 / resample.SPREAD_FLOOR), np.float32(resample.SPREAD_STEPS))
    np.testing.assert_array_equal(got, want)


def test_choice_vocabularies_match_their_implementations():
    from hdrmerge_cli.core.choices import WEIGHTINGS
    from hdrmerge_cli.core.weights import WEIGHTING_FUNCTIONS

    assert set(WEIGHTINGS) == set(WEIGHTING_FUNCTIONS)


def test_raw_merge_imports_no_colour_science(tmp_path, dng_frames):
    """A RAW merge with given noise parameters: no colour-science, matplotlib, cvxpy or
    scipy.stats (the demosaic is the fused kernel; the noise is not measured), and no
    scipy.ndimage (deghosting's; 30 ms of start-up); OpenCV only for the default
    alignment (80 ms of start-up), not with ``--align off``."""
    frames = dng_frames
    heavy = set(HEAVY + ("scipy.ndimage",))
    for align, allowed in (("off", set()), ("auto", {"cv2"})):
        code, mods = _modules_after(["merge", *frames, "-o", str(tmp_path / f"m_{align}.exr"), "-q", "--align", align,
                                     "--noise", "sigma_o2=9,alpha=0.25,beta=0"], tmp_path)
        assert code == 0
        assert not mods & (heavy - allowed), sorted(mods & (heavy - allowed))


@pytest.mark.parametrize("output", ["m.dng", "m.exr --preview PREVIEW"])
def test_previews_import_no_colour_science(tmp_path, dng_frames, output):
    """The DNG's embedded preview and ``--preview`` tone-map without colour-hdri (whose
    package import pulls in colour.plotting and matplotlib: 1.2 s)."""
    name, *extra = output.replace("PREVIEW", str(tmp_path / "p.jpg")).split()
    code, mods = _modules_after(["merge", *dng_frames, "-o", str(tmp_path / name), *extra, "-q", "--align", "off",
                                 "--noise", "sigma_o2=9,alpha=0.25,beta=0"], tmp_path)
    assert code == 0
    assert not mods & set(HEAVY), sorted(mods & set(HEAVY))


def test_summaries_match_the_commands():
    import click

    ctx = click.Context(cli)
    for name in COMMANDS:
        cmd = cli.get_command(ctx, name)
        stub = click.Command(name, help=SUMMARIES[name])
        for limit in (45, 60, 1000):
            assert stub.get_short_help_str(limit) == cmd.get_short_help_str(limit), name


def test_group_help_lists_every_command():
    result = CliRunner().invoke(cli, ["--help"])
    assert result.exit_code == 0
    for name in COMMANDS:
        assert f"  {name}  " in result.output


# ------------------------------------------------------------------ fused colour kernel
MATRIX = np.array([[1.6, -0.4, -0.2], [-0.2, 1.4, -0.2], [0.05, -0.5, 1.45]], np.float32)
WB = np.array([2.1, 1.0, 1.6], np.float32)


def _reference(mosaic, pattern, wb=WB, matrix=MATRIX):
    balanced = mosaic * wb[bayer_channels(pattern, mosaic.shape)]
    return camera_to_rec709(demosaic(balanced, pattern), matrix)


@pytest.mark.parametrize("pattern", ["RGGB", "BGGR", "GRBG", "GBRG"])
@pytest.mark.parametrize("shape", [(40, 36), (33, 17), (5, 6), (3, 4)])
def test_fused_colour_matches_reference(pattern, shape):
    rng = np.random.default_rng(sum(shape))
    mosaic = (rng.random(shape) * rng.choice([1.0, 100.0, 1e4], size=shape)).astype(np.float32)
    ref = _reference(mosaic, pattern)
    got = np.concatenate([raw_to_rgb_rows(mosaic, pattern, WB, MATRIX, y0, min(shape[0], y0 + 8))
                          for y0 in range(0, shape[0], 8)])
    assert got.dtype == np.float32 and got.shape == ref.shape
    scale = np.abs(ref) + 1e-4 * np.abs(ref).max()
    assert np.max(np.abs(got - ref) / scale) < 2e-5


def test_merge_output_equals_reference_colour_path(tmp_path, dng_frames, monkeypatch):
    import hdrmerge_cli.pipeline.output as pm

    frames = dng_frames
    args = ["merge", *frames, "--noise", "sigma_o2=9,alpha=0.25,beta=0", "-q"]
    assert CliRunner().invoke(cli, args + ["-o", str(tmp_path / "fused.exr")]).exit_code == 0
    monkeypatch.setattr(pm, "_raw_to_rgb_rows", raw_to_rgb_rows_reference)
    assert CliRunner().invoke(cli, args + ["-o", str(tmp_path / "ref.exr")]).exit_code == 0
    fused, _ = read_exr(tmp_path / "fused.exr")
    ref, _ = read_exr(tmp_path / "ref.exr")
    assert fused.shape == ref.shape
    np.testing.assert_allclose(fused, ref, rtol=2e-5, atol=1e-6 * float(np.abs(ref).max()))


# ------------------------------------------------------------------ EXR compression
def test_compression_auto_is_lossless_and_by_type():
    assert exr_compression("auto", half=False) == "none"
    assert exr_compression("auto", half=True) == "zips"
    assert exr_compression("piz", half=False) == "piz"
    with pytest.raises(Exception):
        exr_compression("lzma", half=False)


@pytest.mark.parametrize("compression", ["auto", "zip", "piz", "zips"])
def test_merge_compression_option(tmp_path, dng_frames, compression):
    import OpenImageIO as oiio

    frames = dng_frames
    out = tmp_path / f"{compression}.exr"
    result = CliRunner().invoke(cli, ["merge", *frames, "-o", str(out), "-q", "--compression", compression,
                                      "--noise", "sigma_o2=9,alpha=0.25,beta=0"])
    assert result.exit_code == 0, result.output
    inp = oiio.ImageInput.open(str(out))
    try:
        assert inp.spec().get_string_attribute("compression") == exr_compression(compression, False)
    finally:
        inp.close()
    if compression != "auto":  # lossless: the same pixels as the default
        base = tmp_path / "base.exr"
        if not base.exists():
            CliRunner().invoke(cli, ["merge", *frames, "-o", str(base), "-q",
                                     "--noise", "sigma_o2=9,alpha=0.25,beta=0"])
        np.testing.assert_array_equal(read_exr(out)[0], read_exr(base)[0])


def test_compression_choices_are_the_registry():
    result = CliRunner().invoke(cli, ["merge", "--help"])
    for name in EXR_COMPRESSIONS:
        assert name in result.output


# ------------------------------------------------------------------ noise cache
@pytest.fixture
def cam_bracket(tmp_path, dng_frames):
    """The simulated bracket rewritten with a real-looking make/model (simulated sensors
    are never cached)."""
    import rawpy

    from hdrmerge_cli.io.frames import read_frame
    from hdrmerge_cli.io.dng_integer import write_dng

    out = []
    for p in dng_frames:
        f = read_frame(str(p))
        with rawpy.imread(str(p)) as raw:
            mosaic = raw.raw_image_visible.copy()
        dst = tmp_path / "cam" / Path(p).name
        dst.parent.mkdir(exist_ok=True)
        write_dng(str(dst), mosaic, pattern=f.cfa_pattern, black=int(f.black[0]), white=int(f.white[0]),
                  exposure_time=f.exposure_time, iso=int(f.iso), make="TestCam", model="Model X",
                  xyz_to_camera=np.eye(3))
        out.append(str(dst))
    return out


def _merge_json(frames, out, *extra):
    result = CliRunner().invoke(cli, ["merge", *frames, "-o", str(out), "--json", "-q", *extra])
    assert result.exit_code == 0, result.output
    return json.loads(result.output)


def test_noise_cache_fill_hit_and_no_cache(tmp_path, cam_bracket, monkeypatch):
    monkeypatch.setenv("HDRMERGE_CLI_CACHE_DIR", str(tmp_path / "cache"))
    first = _merge_json(cam_bracket, tmp_path / "a.exr")
    assert first["noise_source"].startswith("measured on the bracket")
    stored = json.loads((tmp_path / "cache" / "noise.json").read_text())
    assert len(stored["entries"]) == 1 and "TestCam | Model X | iso=" in next(iter(stored["entries"]))
    second = _merge_json(cam_bracket, tmp_path / "b.exr")
    assert "cache" in second["noise_source"]
    assert second["noise"] == first["noise"]
    assert "noise_estimate" in second["timing_seconds"]
    np.testing.assert_array_equal(read_exr(tmp_path / "a.exr")[0], read_exr(tmp_path / "b.exr")[0])
    profile = json.loads((tmp_path / "b.profile.json").read_text())
    assert profile["noise"]["estimated_from_bracket"]["cached"]["key"].startswith("TestCam")
    # --no-cache: measured again, nothing read or written
    (tmp_path / "cache" / "noise.json").unlink()
    third = _merge_json(cam_bracket, tmp_path / "c.exr", "--no-cache")
    assert third["noise_source"].startswith("measured on the bracket")
    assert not (tmp_path / "cache" / "noise.json").exists()


def test_noise_cache_ignores_damaged_file_and_simulated_frames(tmp_path, cam_bracket, dng_frames, monkeypatch):
    monkeypatch.setenv("HDRMERGE_CLI_CACHE_DIR", str(tmp_path / "cache"))
    (tmp_path / "cache").mkdir()
    (tmp_path / "cache" / "noise.json").write_text("{not json")
    assert _merge_json(cam_bracket, tmp_path / "a.exr")["noise_source"].startswith("measured on the bracket")
    assert json.loads((tmp_path / "cache" / "noise.json").read_text())["schema"] == noisecache.SCHEMA
    from hdrmerge_cli.io.frames import read_frame

    assert noisecache.cache_key(read_frame(dng_frames[0])) is None  # simulated: never cached


def test_cache_location(monkeypatch, tmp_path):
    monkeypatch.delenv("HDRMERGE_CLI_CACHE_DIR", raising=False)
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path))
    assert noisecache.cache_file() == tmp_path / "hdrmerge-cli" / "noise.json"
    monkeypatch.setenv("HDRMERGE_CLI_CACHE_DIR", str(tmp_path / "x"))
    assert noisecache.cache_file() == tmp_path / "x" / "noise.json"


# ------------------------------------------------------------------ sRGB without colour-science
def test_srgb_transfer_functions_equal_colour_science():
    from benchmarks import quiet_import
    from hdrmerge_cli.core.crf import srgb_eotf, srgb_eotf_inverse

    models = quiet_import("colour.models")
    # colour's own default precision (the reference demosaic sets float32 process-wide)
    quiet_import("colour").utilities.set_default_float_dtype(np.float64)
    v = np.concatenate([np.linspace(-0.2, 1.3, 20001), [0.04045, 0.0031308 * 12.92, 0.0031308, 0.0, 1.0]])
    np.testing.assert_array_equal(srgb_eotf(v), models.eotf_sRGB(v))
    np.testing.assert_array_equal(srgb_eotf_inverse(v), models.eotf_inverse_sRGB(v))


def test_image_merge_imports_no_colour_science(tmp_path, jpeg_bracket):
    frames = [str(p) for p in frames_of(*jpeg_bracket)]
    code, mods = _modules_after(["merge", *frames, "-o", str(tmp_path / "j.exr"), "-q", "--crf", "srgb"], tmp_path)
    assert code == 0
    assert not mods & set(HEAVY), sorted(mods & set(HEAVY))


def test_raw_metadata_carries_the_cfa_cell_and_reads_in_parallel(dng_frames, monkeypatch):
    """read_frame keeps LibRaw's 2 x 2 colour index cell it reads while unpacking (so the
    merge does not open and unpack the file again for it): equal to the window read from
    the file; read_bracket reads several frames on two threads and keeps their order."""
    from hdrmerge_cli.io import frames as io_frames
    from hdrmerge_cli.pipeline import bracket

    paths = [str(p) for p in dng_frames]
    frame = io_frames.read_frame(paths[0])
    np.testing.assert_array_equal(frame.cfa_cell, io_frames.raw_channel_window(paths[0])[:2, :2])
    threads = set()
    real = bracket.read_frame

    def spy(path, held=None):
        import threading
        threads.add(threading.current_thread().name)
        return real(path, held)

    monkeypatch.setattr(bracket, "read_frame", spy)
    read = bracket.read_bracket(paths[::-1])
    assert sorted(f.path for f in read) == sorted(paths)
    assert threads and all(t != "MainThread" for t in threads)
    assert [f.exposure_time for f in read] == sorted(f.exposure_time for f in read)


def test_one_malloc_arena_is_set_on_glibc_unless_the_user_chose(monkeypatch):
    """The command asks glibc for one malloc arena (a thread's freed frames otherwise stay
    in its own arena and add to the peak); a user's MALLOC_ARENA_MAX is left alone."""
    import platform

    from hdrmerge_cli.io.malloc import one_malloc_arena

    monkeypatch.delenv("MALLOC_ARENA_MAX", raising=False)
    if sys.platform.startswith("linux") and platform.libc_ver()[0] == "glibc":
        assert one_malloc_arena() is True
    monkeypatch.setenv("MALLOC_ARENA_MAX", "4")
    assert one_malloc_arena() is False
