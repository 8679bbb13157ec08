"""I/O: DNG round trip, EXR, profiles, exposure times, CRF tables."""
import json

import numpy as np
import pytest

from hdrmerge_cli.core.crf import CRF
from hdrmerge_cli.core.errors import HdrMergeError
from hdrmerge_cli.io.atomic import UMASK, write_text, write_together
from hdrmerge_cli.io.crfspec import read_crf_csv, resolve_crf
from hdrmerge_cli.io.frames import load_codes, read_frame
from hdrmerge_cli.io.images import read_exr, write_exr
from conftest import save_profile
from hdrmerge_cli.io.profile import SCHEMA_VERSION, dumps, load_profile, new_profile
from hdrmerge_cli.io.dng_integer import write_dng
from hdrmerge_cli.io.times import parse_seconds, parse_times, read_times_file


def test_dng_round_trip_is_bit_exact_with_metadata(tmp_path):
    rng = np.random.default_rng(0)
    mosaic = rng.integers(0, 4096, (32, 48)).astype(np.uint16)
    path = tmp_path / "x.dng"
    write_dng(str(path), mosaic, pattern="GRBG", black=128, white=4095, exposure_time=1 / 250, iso=400, aperture=5.6)
    frame = read_frame(path)
    assert np.array_equal(load_codes(frame), mosaic)
    assert frame.exposure_time == pytest.approx(1 / 250, rel=1e-6)
    assert frame.iso == 400 and frame.aperture == pytest.approx(5.6)
    assert frame.cfa_pattern == "GRBG" and frame.black.tolist() == [128] * 4 and frame.white[0] == 4095
    np.testing.assert_allclose(frame.color_matrix, np.eye(3), atol=2e-3)  # camera RGB = Rec.709


@pytest.mark.parametrize("half", [False, True])
def test_exr_round_trip(tmp_path, half):
    data = np.random.default_rng(1).random((6, 7, 3)).astype(np.float32) * 100
    write_exr(str(tmp_path / "a.exr"), data, ["R", "G", "B"], {"hdrmerge:referenceExposure": 0.5}, half=half)
    back, attrs = read_exr(tmp_path / "a.exr")
    np.testing.assert_allclose(back, data, rtol=1e-3 if half else 0)
    assert attrs["compression"] == ("zips" if half else "none")  # --compression auto: lossless, by type
    assert attrs["hdrmerge:referenceExposure"] == 0.5


def test_exr_refuses_non_finite(tmp_path):
    with pytest.raises(HdrMergeError):
        write_exr(str(tmp_path / "a.exr"), np.array([[[np.nan]]]), ["Y"], {})


def test_profile_round_trips_exactly_and_keeps_unknown_keys(tmp_path):
    table = np.linspace(0, 1, 256) ** 2.2 + 1e-17 * np.arange(256)
    from hdrmerge_cli.core.crf import table_crf

    prof = new_profile({"make": "A", "model": "B"}, 8, table_crf(np.stack([table] * 3)), ["a.jpg"], "test")
    prof["future_key"] = {"x": [1, 2.5]}
    save_profile(tmp_path / "p.json", prof, overwrite=False)
    back = load_profile(tmp_path / "p.json")
    assert back == prof and dumps(back) == (tmp_path / "p.json").read_text()


def test_profile_validation_errors(tmp_path):
    p = tmp_path / "p.json"
    p.write_text(json.dumps({"schema": 1, "kind": "hdrmerge-cli camera profile", "crf": {"model": "gamma"}}))
    with pytest.raises(HdrMergeError, match="gamma"):
        load_profile(p)
    p.write_text(json.dumps({"schema": SCHEMA_VERSION + 1, "kind": "x", "crf": {}}))
    with pytest.raises(HdrMergeError, match="newer"):
        load_profile(p)
    p.write_text("{not json")
    with pytest.raises(HdrMergeError, match="not JSON"):
        load_profile(p)


def test_times_parsing(tmp_path):
    assert parse_times("1/100, 1/25,0.5") == [0.01, 0.04, 0.5]
    assert parse_seconds('2"') == 2.0
    for bad in ("0", "-1", "x", "1/0"):
        with pytest.raises(HdrMergeError):
            parse_seconds(bad)
    f = tmp_path / "t.txt"
    f.write_text("# comment\na.jpg 1/100\nsub/b.jpg 0.5\n")
    assert read_times_file(str(f)) == {"a.jpg": 0.01, "b.jpg": 0.5}
    f.write_text("a.jpg\n")
    with pytest.raises(HdrMergeError, match=":1:"):
        read_times_file(str(f))


def test_crf_csv_and_names(tmp_path):
    f = tmp_path / "crf.csv"
    z = np.arange(0, 256, 5)
    f.write_text("z,linear\n" + "\n".join(f"{a},{(a / 255) ** 2}" for a in z))
    crf = read_crf_csv(str(f))
    assert crf.table.shape == (1, 256)
    np.testing.assert_allclose(crf.inverse(np.array([0.5])), [0.25], atol=2e-3)
    assert resolve_crf("gamma:2.4") == CRF("gamma", 2.4)
    f.write_text("z,linear\n0,0.5\n10,0.2\n")
    with pytest.raises(HdrMergeError, match="monotone"):
        read_crf_csv(str(f))
    for bad in ("gamma", "gamma:-1", "srgb:2", "cubic"):
        with pytest.raises(HdrMergeError):
            resolve_crf(bad)


def test_atomic_outputs_get_the_umask_mode_or_keep_the_replaced_files(tmp_path):
    """mkstemp's 0600 must not leak into the outputs: a new file gets 0666 & ~umask, an
    overwritten one keeps its mode."""
    fresh, kept = tmp_path / "a.txt", tmp_path / "b.txt"
    write_together([(fresh, lambda tmp: write_text(tmp, "x"))], overwrite=False)
    assert fresh.stat().st_mode & 0o777 == 0o666 & ~UMASK
    kept.write_text("old")
    kept.chmod(0o640)
    write_together([(kept, lambda tmp: write_text(tmp, "new"))], overwrite=True)
    assert kept.stat().st_mode & 0o777 == 0o640 and kept.read_text() == "new"


def test_silencing_c_stderr_from_many_threads_restores_it():
    """Frames decode on several threads: however their silenced spans overlap, file
    descriptor 2 must end up where it was, never on /dev/null."""
    import os
    import threading
    import time

    from hdrmerge_cli.io.frames import quiet_c_stderr

    before = os.fstat(2)
    null = os.stat(os.devnull)
    seen = []

    def work(k):
        with quiet_c_stderr():
            seen.append(os.fstat(2).st_ino == null.st_ino)
            time.sleep(0.001 * (k % 3))

    threads = [threading.Thread(target=work, args=(k,)) for k in range(24)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    after = os.fstat(2)
    assert all(seen) and (after.st_dev, after.st_ino) == (before.st_dev, before.st_ino)
