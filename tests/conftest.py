"""Shared fixtures: the installed command, simulated brackets, the shared data folder."""
from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np
import pytest

SHARED = Path(__file__).resolve().parents[1].parent / "shared" / "data"
# merges measure noise afresh: no per-camera cache from the user's home or another test
os.environ["HDRMERGE_CLI_CACHE_DIR"] = tempfile.mkdtemp(prefix="hdrmerge-cli-test-cache-")
needs_shared = pytest.mark.skipif(not SHARED.is_dir(), reason=f"shared test data not found at {SHARED}")


def _command() -> list[str]:
    exe = Path(sys.executable).parent / "hdrmerge-cli"
    if exe.exists():
        return [str(exe)]
    found = shutil.which("hdrmerge-cli")
    return [found] if found else [sys.executable, "-m", "hdrmerge_cli"]


@pytest.fixture(scope="session")
def run():
    """Run the installed ``hdrmerge-cli``; returns the CompletedProcess (text)."""
    cmd = _command()

    def _run(*args, check: bool = True, cwd=None):
        proc = subprocess.run(cmd + [str(a) for a in args], capture_output=True, text=True, cwd=cwd,
                              env=os.environ | {"PYTHONWARNINGS": "ignore"})
        if check and proc.returncode != 0:
            raise AssertionError(f"hdrmerge-cli {' '.join(map(str, args))} failed ({proc.returncode}):\n{proc.stderr}")
        return proc

    return _run


def _simulate(run, folder: Path, *args) -> dict:
    run("simulate", "-o", folder, "-q", *args)
    return json.loads((folder / "simulation.json").read_text())


@pytest.fixture(scope="session")
def dng_bracket(tmp_path_factory, run):
    """5 DNG frames of the built-in scene, 256 x 192."""
    folder = tmp_path_factory.mktemp("dng")
    meta = _simulate(run, folder, "--size", "256x192", "--frames", "5", "--seed", "3")
    return folder, meta


@pytest.fixture(scope="session")
def tiff_bracket(tmp_path_factory, run):
    """4 16-bit TIFF frames through a gamma 2.2 CRF."""
    folder = tmp_path_factory.mktemp("tif")
    meta = _simulate(run, folder, "--size", "192x128", "--frames", "4", "--format", "tif", "--out-bits", "16",
                     "--crf", "gamma:2.2", "--seed", "4")
    return folder, meta


@pytest.fixture(scope="session")
def jpeg_bracket(tmp_path_factory, run):
    """3 JPEG frames through the sRGB CRF."""
    folder = tmp_path_factory.mktemp("jpg")
    meta = _simulate(run, folder, "--size", "192x128", "--frames", "3", "--format", "jpg", "--seed", "5")
    return folder, meta


def save_profile(path, profile: dict, overwrite: bool) -> None:
    """Write a profile as the commands do (checked, atomically)."""
    from hdrmerge_cli.io.atomic import write_together
    from hdrmerge_cli.io.profile import profile_writer

    write_together([(path, profile_writer(profile, path))], overwrite)


def frames_of(folder: Path, meta: dict, which=None) -> list[Path]:
    names = meta["frames"] if which is None else [meta["frames"][k] for k in which]
    return [folder / n for n in names]


def log_rmse(estimate: np.ndarray, truth: np.ndarray, margin: int = 0) -> float:
    """RMS of log(estimate) - log(truth) over pixels where both are positive."""
    if margin:
        estimate, truth = estimate[margin:-margin, margin:-margin], truth[margin:-margin, margin:-margin]
    ok = (truth > 0) & (estimate > 0)
    return float(np.sqrt(np.mean((np.log(estimate[ok]) - np.log(truth[ok])) ** 2)))
