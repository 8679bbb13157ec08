"""merge --batch: group a folder into brackets and merge each, on local processes or a
Dask cluster, continuing past bad brackets."""
from __future__ import annotations

import contextlib
import dataclasses
import datetime as _dt
import logging
import os
import signal
import tempfile
import time
import uuid
from concurrent.futures import ProcessPoolExecutor, as_completed
from concurrent.futures.process import BrokenProcessPool
from dataclasses import dataclass
from multiprocessing import get_context
from pathlib import Path

import numpy as np

from hdrmerge_cli.core.errors import HdrMergeError, Terminated, raise_terminated
from hdrmerge_cli.core.similarity import SAME_SCENE_CORRELATION, same_scene, structure_correlation
from hdrmerge_cli.io.atomic import output_folder
from hdrmerge_cli.io.frames import Frame, list_frames, read_frame, separate_python_stderr
from hdrmerge_cli.io.logs import StderrFormatter
from hdrmerge_cli.io.malloc import one_malloc_arena
from hdrmerge_cli.io.thumbnails import read_thumbnail, thumbnail_shape
from hdrmerge_cli.io.metadata import fmt_time
from hdrmerge_cli.pipeline.run import merge
from hdrmerge_cli.pipeline.options import DEFAULT_GAP, MergeOptions
from hdrmerge_cli.pipeline.output import default_profile_path

log = logging.getLogger("hdrmerge_cli")

#: exposure times within this many stops count as the same setting (cameras round the
#: times they record; bracket steps are 1/3 stop or more)
SAME_SETTING_STOPS = 1 / 6
#: a monotone exposure sequence of at least :data:`RESTART_MIN_FRAMES` frames that turns
#: back by this many stops or more has restarted (the next AEB sequence)
RESTART_FALL_STOPS = 2.0
RESTART_MIN_FRAMES = 3
#: longer side (pixels) of the thumbnails compared across a gap: 192 x 108 for 16:9 frames,
#: about 40,000 gradients, so that neighbours 1-2 EV apart that share a few per cent of the
#: frame well exposed still give the scene test hundreds (a quarter of the side: tens, too few)
THUMBNAIL_SIDE = 192
#: thumbnail values (fraction of full scale, camera-encoded) a frame exposes well
WELL_EXPOSED = (8 / 255, 247 / 255)


def capture_seconds(stamp: str | None) -> float | None:
    """Seconds since the epoch of a frame's timestamp (ISO 8601 from LibRaw, or EXIF's
    ``YYYY:MM:DD HH:MM:SS``); None when absent or unreadable."""
    if not stamp:
        return None
    for parse in (_dt.datetime.fromisoformat, lambda s: _dt.datetime.strptime(s, "%Y:%m:%d %H:%M:%S")):
        try:
            t = parse(stamp.strip())
        except ValueError:
            continue
        return (t if t.tzinfo else t.replace(tzinfo=_dt.timezone.utc)).timestamp()
    return None


@dataclass
class FoundBracket:
    """Frames of one bracket in capture order.  ``reason``: why it was cut from the frames
    before it (None for the folder's first frames); ``joined``: the frames it kept across a
    gap longer than ``--gap`` because they show its scene (frame, gap_seconds,
    same_scene_as, correlation, gradients)."""
    frames: list[Frame]
    reason: str | None
    joined: list[dict] = dataclasses.field(default_factory=list)
    #: the index in ``frames`` where the camera's current auto-bracket sequence started
    sequence: int = 0


def split_brackets(frames: list[Frame], gap: float = DEFAULT_GAP, thumbnail=None) -> list[FoundBracket]:
    """Split frames into brackets, in capture order (timestamp, then file name).

    Frames of different cameras or image layouts (a RAW + JPEG folder) go to separate
    brackets.  Within one layout the camera's bracketing tags decide first where they are
    stated (:func:`bracketing_tags`): a frame that continues the camera's auto-bracket
    sequence stays, one whose exposure mode differs starts a new bracket, and one that
    starts the camera's sequence again joins only where the new sequence extends the
    bracket's range (:func:`_extends`: a photographer adding exposures with a second
    sequence, not retaking an aborted one) and shows the bracket's scene.  Untagged frames: a
    new bracket starts where the exposure sequence started again (:func:`restart_reason`,
    on exposures: time x ISO / N^2, so a camera that changes ISO inside a bracket stays
    whole), or at a frame taken more than ``gap`` seconds after the previous frame's
    exposure ended (both timestamped) unless it adds a new exposure and shows the scene of
    one of the bracket's frames (:func:`~hdrmerge_cli.core.similarity.same_scene` of their
    thumbnails; hand-held brackets are often shot seconds apart).  Frames repeating the
    previous frame's exposure within ``gap`` (a burst) stay together.

    ``thumbnail(frame)``: a 2-D array in [0, 1] (default: :data:`THUMBNAIL_SIDE` pixels from
    :func:`~hdrmerge_cli.io.thumbnails.read_thumbnail`), the same shape for frames of one
    layout; read only for frames on either side of such a gap, once per frame."""
    def key(f):
        t = capture_seconds(f.timestamp)
        return (t if t is not None else float("-inf"), Path(f.path).name)

    scenes = _SceneTest(thumbnail or (lambda frame: read_thumbnail(frame, thumbnail_shape(frame, THUMBNAIL_SIDE))))
    brackets: list[FoundBracket] = []
    open_bracket: dict = {}  # layout -> its current bracket
    previous = None
    for f in sorted(frames, key=key):
        current = open_bracket.get(f.layout)
        if current is None:
            reason = None if previous is None else f"another camera or image layout than {previous.name}"
        else:
            last = current.frames[-1]
            tags = bracketing_tags(current, f)
            after = _seconds_after(last, f)
            if tags is not None:
                verdict, why = tags
                reason = None if verdict == "continues" else why if verdict == "cut" else \
                    _extends(current, f, why) or _join_or_cut(current, f, why, after, scenes)
            else:
                reason = restart_reason(current.frames, f)
                if reason is None and after is not None and after > gap:
                    what = f"{after:.0f} s after {last.name}'s exposure ended (more than --gap {gap:g} s)"
                    if _same_exposure(f, last):  # a burst is quick
                        reason = f"{what}, and the same exposure"
                    else:
                        reason = _join_or_cut(current, f, what, after, scenes)
        if current is None or reason is not None:
            current = open_bracket[f.layout] = FoundBracket([f], reason)
            brackets.append(current)
        else:
            current.frames.append(f)
        previous = f
    return brackets


def _join_or_cut(current: FoundBracket, f: Frame, what: str, after: float | None, scenes) -> str | None:
    """None when ``f`` joins ``current`` across ``what`` (a long gap, a new camera
    sequence): its exposure is new to the bracket and it shows the bracket's scene; else
    why it starts a new bracket."""
    repeated = next((g for g in current.frames if _same_exposure(f, g)), None)
    if repeated is not None:
        return f"{what}, and its exposure ({_describe(f)}) repeats {repeated.name}"
    match, verdict = scenes.match(current.frames, f)
    if match is None:
        return f"{what}, and {verdict}"
    current.joined.append({"frame": f.name, "gap_seconds": None if after is None else round(after, 3), **match})
    current.sequence = len(current.frames)
    return None


def _extends(current: FoundBracket, f: Frame, what: str) -> str | None:
    """None when ``f``, the first frame of a new camera sequence, lies outside the exposures
    the bracket spans (by more than :data:`SAME_SETTING_STOPS`): a sequence that extends the
    range; else why it starts a new bracket (one inside the range retakes it)."""
    t, spans = exposure_of(f), [exposure_of(g) for g in current.frames]
    if t is None or any(x is None for x in spans):
        return None
    lo, hi = np.log2(min(spans)), np.log2(max(spans))
    if np.log2(t) < lo - SAME_SETTING_STOPS or np.log2(t) > hi + SAME_SETTING_STOPS:
        return None
    return f"{what}, within the exposures the bracket spans ({_describe(f)}: a retake, not an extension)"


def bracketing_tags(current: FoundBracket, f: Frame) -> tuple[str, str] | None:
    """What the camera's bracketing tags (EXIF ExposureMode "auto bracket" and
    ExposureBiasValue) say of frame ``f`` after the bracket ``current``, as ``(verdict,
    why)``: ``"continues"`` the camera's sequence; ``"cut"``: its exposure mode changed (an
    auto-bracket frame next to one that is not); ``"restarted"``: ``f``'s compensation
    repeats one of the current sequence's, the camera's next sequence.  None where they say
    nothing (neither ``f`` nor the bracket's last frame is an auto-bracket frame, or a
    compensation is not stated)."""
    last = current.frames[-1]
    if not (f.auto_bracket or last.auto_bracket):
        return None
    if f.auto_bracket != last.auto_bracket:
        return "cut", (f"the camera's exposure mode changed (EXIF ExposureMode: {last.name} "
                       f"{'is' if last.auto_bracket else 'is not'} an auto-bracket frame, {f.name} "
                       f"{'is' if f.auto_bracket else 'is not'})")
    sequence = current.frames[current.sequence:]
    if f.exposure_bias is None or any(g.exposure_bias is None for g in sequence):
        return None
    again = next((g for g in sequence if abs(g.exposure_bias - f.exposure_bias) <= SAME_SETTING_STOPS), None)
    if again is None:
        return "continues", ""
    return "restarted", (f"the camera's auto-bracket sequence started again (compensation "
                         f"{f.exposure_bias:+.2g} EV repeats {again.name})")


def exposure_of(f: Frame) -> float | None:
    """A frame's exposure for grouping: exposure time x ISO / f-number^2 (a factor the
    frame does not state counts as ISO 100, f/1), or None without an exposure time."""
    if f.exposure_time is None:
        return None
    return f.exposure_time * (f.iso or 100.0) / 100.0 / (f.aperture or 1.0) ** 2


def _describe(f: Frame) -> str:
    return fmt_time(f.exposure_time) + (f" at ISO {f.iso:g}" if f.iso else "") + (
        f", f/{f.aperture:g}" if f.aperture else "")


def _seconds_after(last: Frame, f: Frame) -> float | None:
    """Seconds from the end of ``last``'s exposure to the start of ``f``'s (None unless
    both are timestamped)."""
    t, t0 = capture_seconds(f.timestamp), capture_seconds(last.timestamp)
    if t is None or t0 is None:
        return None
    return t - t0 - (last.exposure_time or 0.0)


class _SceneTest:
    """Whether a frame shows the scene of a bracket, on thumbnails read once per frame."""

    def __init__(self, read):
        self.read = read
        self.cache: dict[str, np.ndarray | HdrMergeError] = {}

    def thumbnail(self, frame: Frame) -> np.ndarray:
        if frame.path not in self.cache:
            try:
                self.cache[frame.path] = self.read(frame)
            except HdrMergeError as exc:
                self.cache[frame.path] = exc
        got = self.cache[frame.path]
        if isinstance(got, HdrMergeError):
            raise got
        return got

    def match(self, bracket: list[Frame], f: Frame) -> tuple[dict | None, str]:
        """The first frame of ``bracket`` (nearest exposure first) that ``f`` shows the
        scene of, as ``{"same_scene_as", "correlation", "gradients"}``, or None and why not
        (a phrase naming the closest candidate)."""
        def stops(g):
            if exposure_of(f) is None or exposure_of(g) is None:
                return np.inf
            return abs(np.log2(exposure_of(g) / exposure_of(f)))

        best = None  # (z, r, n, frame) of the strongest evidence
        try:
            b = self.thumbnail(f)
            for g in sorted(bracket, key=stops):
                r, n = structure_correlation(self.thumbnail(g), b, *WELL_EXPOSED)
                if same_scene(r, n):
                    return {"same_scene_as": g.name, "correlation": round(r, 3), "gradients": n}, ""
                if n and (best is None or r * np.sqrt(n) > best[0]):
                    best = (r * np.sqrt(n), r, n, g)
        except HdrMergeError as exc:
            return None, f"its content could not be compared ({exc})"
        if best is None:
            return None, "no part of the scene is well exposed in both it and the bracket's frames"
        _, r, n, g = best
        if r >= SAME_SCENE_CORRELATION:
            return None, (f"too little of the scene is well exposed in both it and {g.name} to tell whether it is the "
                          f"same ({n} gradients)")
        return None, f"a different scene than {g.name} (structure correlation {r:.2f} on {n} gradients)"


def _same_exposure(a: Frame, b: Frame) -> bool:
    """Whether two frames' exposures (:func:`exposure_of`) agree within :data:`SAME_SETTING_STOPS`."""
    ea, eb = exposure_of(a), exposure_of(b)
    return ea is not None and eb is not None and abs(np.log2(ea / eb)) <= SAME_SETTING_STOPS


def restart_reason(current: list[Frame], f: Frame) -> str | None:
    """Why frame ``f`` starts a new exposure sequence after the bracket ``current``, or
    None if it does not (on exposures, :func:`exposure_of`):

    - its exposure repeats one of the bracket (within :data:`SAME_SETTING_STOPS`, the
      rounding of recorded times) other than the previous frame's (repeating the previous
      frame's exposure is a burst, which merges); or
    - the bracket so far is a monotone (ascending or descending) sequence of at least
      :data:`RESTART_MIN_FRAMES` frames and ``f`` turns back from its last frame by
      :data:`RESTART_FALL_STOPS` or more (AEB restarting, even when the new sequence's
      exposures differ slightly from the last one's).  Centre-out orders (0, -, +, --, ++)
      are not monotone from their start, so their turns do not split them."""
    t, prev = exposure_of(f), exposure_of(current[-1])
    if t is None:
        return None
    if not _same_exposure(f, current[-1]):
        for g in current[:-1]:
            if _same_exposure(f, g):
                return f"the exposure sequence started again ({_describe(f)} repeats {g.name})"
    exposures = [exposure_of(g) for g in current]
    if len(exposures) < RESTART_MIN_FRAMES or any(x is None for x in exposures) or prev is None:
        return None
    steps = [np.log2(b / a) for a, b in zip(exposures, exposures[1:])]
    back = np.log2(t / prev)
    for sign, way in ((1, "ascending"), (-1, "descending")):
        if all(sign * s > SAME_SETTING_STOPS for s in steps) and -sign * back >= RESTART_FALL_STOPS - SAME_SETTING_STOPS:
            return (f"the exposure sequence started again (the {way} sequence turns back "
                    f"{abs(back):.1f} stops at {_describe(f)})")
    return None


@dataclass
class BatchOptions:
    folder: str
    outdir: Path
    merge: MergeOptions
    jobs: int = 1
    gap: float = DEFAULT_GAP
    scheduler: str | None = None
    skip_existing: bool = False


def plan(opts: BatchOptions) -> list[dict]:
    """The brackets of the folder, each ``{"frames": [...], "output": ..., "reason": ...}``
    (``reason``: why it was cut from the frames before it, see :func:`split_brackets`;
    ``joined``: the long gaps it was kept together across); unreadable files are reported
    as their own failed entries (``"error"``), files that are no bracket's frame
    (:func:`left_out`) are left out with a warning.  A bracket of one frame is warned about."""
    frames, bad = [], []
    paths = list_frames(opts.folder)
    if not paths:
        raise HdrMergeError(f"{opts.folder}: no frames to merge in this folder")
    for p in paths:
        p = str(Path(p).resolve())  # absolute: cluster workers do not share our working directory
        try:
            frame = read_frame(p)
        except HdrMergeError as exc:
            log.error("%s", exc)
            bad.append({"frames": [p], "output": None, "status": "failed", "error": str(exc)})
            continue
        why = left_out(frame)
        if why:
            log.warning("%s: %s; left out of the batch", p, why)
        else:
            frames.append(frame)
    out, taken = [], set()
    outdir = Path(opts.outdir).resolve()
    brackets = split_brackets(frames, opts.gap)
    for k, bracket in enumerate(brackets):
        group = bracket.frames
        first = Path(group[0].path)
        name = first.stem if first.stem not in taken else f"{first.stem}_{first.suffix.lstrip('.').lower()}"
        n = 2
        while name in taken:  # unique output names: never two brackets on one file
            name, n = f"{first.stem}_{n}", n + 1
        taken.add(name)
        output = outdir / (name + ".exr")
        entry = {"frames": [f.path for f in group], "output": str(output), "status": "planned",
                 "reason": bracket.reason, "joined": bracket.joined}
        if len(group) == 1:
            log.warning("%s", _single_frame_warning(bracket, brackets[k + 1:]))
        if opts.skip_existing and output.exists() and all(
                output.stat().st_mtime >= os.stat(f.path).st_mtime for f in group):
            entry["status"] = "skipped"
        out.append(entry)
    return out + bad


def left_out(frame: Frame) -> str | None:
    """Why ``frame`` is no bracket's frame, or None: hdrmerge-cli wrote it (its Software tag:
    a merge's preview), or it states no exposure time (EXIF ExposureTime), which a batch
    cannot be told."""
    if "software=hdrmerge-cli" in frame.style.lower():
        return "written by hdrmerge-cli (a merge's preview), not a camera's frame"
    if frame.exposure_time is None:
        return "no exposure time (EXIF ExposureTime)"
    return None


def _single_frame_warning(bracket: FoundBracket, later: list[FoundBracket]) -> str:
    """One line: the frame, and why it was cut from the frames before and after it."""
    f = bracket.frames[0]
    nxt = next((b for b in later if b.frames[0].layout == f.layout), None)
    why = [f"before it: {bracket.reason}" if bracket.reason else "it is the first frame"]
    why.append(f"after it: {nxt.frames[0].name}: {nxt.reason}" if nxt else "no frame follows it")
    return f"{f.path}: a bracket of one frame, merged alone ({'; '.join(why)})"


def merge_one(paths: list[str], opts: MergeOptions, profile_text: str | None = None,
              started: float | None = None) -> dict:
    """Merge one bracket; never raises for a bad bracket: returns ``{"status": "failed",
    "error": ...}`` instead.  ``profile_text``: the --profile JSON, sent once to a cluster's
    workers (their file systems may not hold it).  ``started``: the batch's start time on a
    cluster, where a task may run again after its worker died: outputs this batch already
    wrote for it (the EXR and its profile, both newer than ``started``) count as done."""
    io = opts.io
    profile_out = Path(io.profile_out) if io.profile_out else default_profile_path(Path(io.output))
    if started is not None and all(p.exists() and p.stat().st_mtime >= started for p in (io.output, profile_out)):
        return {"status": "merged", "summary": {"output": str(io.output), "profile": str(profile_out),
                                                "retried": True}}
    try:
        if profile_text is not None:
            with tempfile.TemporaryDirectory() as tmp:
                profile = Path(tmp) / "profile.json"
                profile.write_text(profile_text, encoding="utf-8")
                return {"status": "merged", "summary": merge(paths, opts.replace(profile=str(profile)))}
        return {"status": "merged", "summary": merge(paths, opts)}
    except HdrMergeError as exc:
        return {"status": "failed", "error": str(exc)}
    except MemoryError:
        return {"status": "failed", "error": "out of memory: merge fewer or smaller frames (or fewer --jobs)"}
    except OSError as exc:
        return {"status": "failed", "error": f"{exc.filename + ': ' if exc.filename else ''}{exc.strerror or exc}"}
    except Exception as exc:  # a bug must not cost the other brackets; -vv shows where
        log.debug("bracket %s", paths[0], exc_info=True)
        return {"status": "failed", "error": f"internal error ({type(exc).__name__}: {exc}); please report it"}


def run_batch(opts: BatchOptions, entries: list[dict], progress=None) -> dict:
    """Merge the planned brackets of ``entries`` (from :func:`plan`): ``jobs`` local
    processes, or the Dask cluster at ``scheduler`` (one task per bracket; the profile
    sent to the workers once).  ``progress(n)`` is called as brackets finish.  Returns the
    batch summary; the caller decides the exit status from ``summary["failed"]``."""
    todo = [e for e in entries if e["status"] == "planned"]
    profile = opts.merge.inputs.profile
    profile_text = Path(profile).read_text(encoding="utf-8") if profile else None
    jobs = [(e, opts.merge.replace(output=Path(e["output"]), profile_out=None)) for e in todo]
    client = _connect(opts.scheduler) if opts.scheduler and jobs else None  # before anything is created
    # nothing to write: no output folder either; interrupted, or every bracket failed: the
    # folders made for the outputs go again
    with output_folder(opts.outdir) if todo else contextlib.nullcontext():
        if client is not None:
            with client:
                results = _on_dask(client, jobs, profile_text, progress)
        elif opts.jobs > 1 and len(jobs) > 1:
            results = _on_processes(opts.jobs, jobs, progress)
        else:
            results = []
            for e, mo in jobs:
                results.append((e, merge_one(e["frames"], mo)))
                if progress:
                    progress(1)
    for e, res in results:
        e["status"] = res["status"]
        if res["status"] == "failed":
            e["error"] = res["error"]
            log.error("bracket %s: %s", Path(e["frames"][0]).name, res["error"])
        else:
            e["profile"] = res["summary"]["profile"]
    return summarize(entries)


#: a worker process is merging a bracket (its stop signal then unwinds the merge)
_IN_JOB = False


def _stop_worker(signum, frame):
    """A worker's SIGTERM/SIGINT handler: inside a merge, unwind it (removing its
    temporaries, see :func:`_merge_in_worker`); between merges, exit at once."""
    if _IN_JOB:
        raise_terminated(signum, frame)
    os._exit(128 + signum)


def _init_worker(level: int) -> None:
    """Worker processes log like the parent (prefix, level, stderr) and stop on SIGTERM
    or Ctrl-C (removing their temporaries) when the parent stops them."""
    separate_python_stderr()
    one_malloc_arena()
    for sig in (signal.SIGTERM, signal.SIGINT):
        signal.signal(sig, _stop_worker)
    handler = logging.StreamHandler()
    handler.setFormatter(StderrFormatter())
    log.handlers[:] = [handler]
    log.setLevel(level)
    log.propagate = False


def _merge_in_worker(paths, opts):
    """:func:`merge_one` in a worker process.  A stop signal unwinds the merge (its
    temporaries removed), then the process exits: it must not go on to a bracket the pool
    had already queued for it (the pool's queued calls cannot be cancelled)."""
    global _IN_JOB
    _IN_JOB = True
    try:
        return merge_one(paths, opts)
    except Terminated as exc:
        os._exit(128 + exc.signum)
    finally:
        _IN_JOB = False


def _on_processes(n: int, jobs, progress):
    # spawn: a fresh interpreter per worker (forking a process whose numba threads run is unsafe)
    with ProcessPoolExecutor(n, mp_context=get_context("spawn"), initializer=_init_worker,
                             initargs=(log.getEffectiveLevel(),)) as pool:
        futures = {pool.submit(_merge_in_worker, e["frames"], mo): e for e, mo in jobs}
        results = []
        try:
            for fut in as_completed(futures):
                try:
                    res = fut.result()
                except BrokenProcessPool:
                    res = {"status": "failed", "error": "its worker process died (out of memory? try fewer --jobs)"}
                results.append((futures[fut], res))
                if progress:
                    progress(1)
        except BaseException:  # Ctrl-C, SIGTERM/SIGHUP: no further bracket starts, the running ones stop
            procs = list((getattr(pool, "_processes", None) or {}).values())
            pool.shutdown(wait=False, cancel_futures=True)
            for proc in procs:
                proc.terminate()
            for proc in procs:  # they remove their temporaries; nothing is written after we return
                proc.join(timeout=30)
            raise
    return results


def _connect(address: str):
    """A Dask client, or a one-line error; distributed's own logging kept off stderr."""
    try:
        from distributed import Client
    except ImportError:
        raise HdrMergeError("--scheduler needs Dask: pip install 'hdrmerge-cli[cluster]'") from None
    logging.getLogger("distributed").setLevel(logging.CRITICAL)
    try:
        return Client(address, timeout="10s")
    except (OSError, TimeoutError) as exc:
        raise HdrMergeError(f"cannot reach the Dask scheduler at {address} ({exc})") from None


def _on_dask(client, jobs, profile_text, progress):
    from distributed import as_completed as dask_completed

    shared = client.scatter(profile_text, broadcast=True) if profile_text is not None else None
    run_id = uuid.uuid4().hex[:12]  # keys unique to this run: two batches never share a task
    started = time.time()
    futures = {client.submit(merge_one, e["frames"], mo, shared, started, pure=False,
                             key=f"merge-{run_id}-{i}-{Path(e['output']).stem}"): e
               for i, (e, mo) in enumerate(jobs)}
    results = []
    try:
        for fut in dask_completed(futures):
            try:
                res = fut.result()
            except Exception as exc:  # e.g. a worker killed: that bracket fails, the batch goes on
                res = {"status": "failed", "error": f"the cluster lost this task ({type(exc).__name__}: {exc})"}
            results.append((futures[fut], res))
            if progress:
                progress(1)
    except Exception as exc:  # the scheduler is gone: one line for each bracket not reported
        done = {id(e) for e, _ in results}
        results += [(e, {"status": "failed", "error": f"lost the Dask scheduler ({type(exc).__name__})"})
                    for e in futures.values() if id(e) not in done]
    except BaseException:  # Ctrl-C, SIGTERM/SIGHUP: the cluster stops this run's tasks
        client.cancel(list(futures), force=True)
        raise
    return results


def summarize(entries: list[dict]) -> dict:
    counts = {s: sum(e["status"] == s for e in entries) for s in ("merged", "skipped", "failed", "planned")}
    return {"brackets": entries, **counts}


def describe(summary: dict) -> str:
    """One line per bracket for the terminal (the --dry-run listing): status, output,
    frames, then why the bracket was cut from the frames before it and any long gap it
    was kept together across."""
    lines = []
    for e in summary["brackets"]:
        names = ", ".join(Path(p).name for p in e["frames"])
        target = e["output"] or "-"
        notes = [e["error"]] if e.get("error") else []
        notes += [f"new bracket: {e['reason']}"] if e.get("reason") else []
        if e.get("joined"):
            gaps = ", ".join(f"{j['gap_seconds']:.0f} s before {j['frame']}" for j in e["joined"])
            notes.append(f"kept together across long gaps, the same scene: {gaps}")
        lines.append(f"{e['status']:8} {target}  <- {names}" + "".join(f"  ({n})" for n in notes))
    return "\n".join(lines)
