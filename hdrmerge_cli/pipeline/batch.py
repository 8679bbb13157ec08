"""merge --batch: group a folder into brackets and merge each, on local processes or a
Dask cluster, continuing past bad brackets."""
from __future__ import annotations

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
from hdrmerge_cli.io.frames import Frame, list_frames, read_frame, separate_python_stderr
from hdrmerge_cli.io.logs import StderrFormatter
from hdrmerge_cli.io.memory import one_malloc_arena
from hdrmerge_cli.pipeline.merge import merge
from hdrmerge_cli.pipeline.options import MergeOptions
from hdrmerge_cli.pipeline.output import default_profile_path

log = logging.getLogger("hdrmerge_cli")

#: default largest capture-time gap (s) inside one bracket (HDRMerge's -g default)
DEFAULT_GAP = 3.0
#: exposure times within this many stops count as the same setting (cameras round the
#: times they record; bracket steps are 1/3 stop or more)
SAME_SETTING_STOPS = 1 / 6
#: an ascending exposure sequence of at least :data:`RESTART_MIN_FRAMES` frames that falls
#: back by this many stops or more has restarted (the next AEB sequence)
RESTART_FALL_STOPS = 2.0
RESTART_MIN_FRAMES = 3


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


def group_brackets(frames: list[Frame], gap: float = DEFAULT_GAP) -> list[list[Frame]]:
    """Split frames into brackets, in capture order (timestamp, then file name).

    Frames of different cameras or image layouts (a RAW + JPEG folder) go to separate
    brackets.  Within one layout a new bracket starts at a frame taken more than ``gap``
    seconds after the bracket's last frame (when both have timestamps), or where the
    camera's exposure sequence started again (:func:`restarts`): its exposure time repeats
    an earlier one of the bracket, or an ascending sequence falls back by a couple of
    stops.  Frames repeating the previous frame's time (a burst) stay together."""
    def key(f):
        t = capture_seconds(f.timestamp)
        return (t if t is not None else float("-inf"), Path(f.path).name)

    groups: list[list[Frame]] = []
    open_group: dict = {}  # layout -> index of its current bracket in groups
    for f in sorted(frames, key=key):
        t = capture_seconds(f.timestamp)
        k = open_group.get(f.layout)
        current = None if k is None else groups[k]
        last_t = None if current is None else capture_seconds(current[-1].timestamp)
        new = (
            current is None
            or (t is not None and last_t is not None and t - last_t > gap)
            or restarts(current, f)
        )
        if new:
            open_group[f.layout] = len(groups)
            groups.append([f])
        else:
            current.append(f)
    return groups


def _same_time(a, b) -> bool:
    return a is not None and b is not None and abs(np.log2(a / b)) <= SAME_SETTING_STOPS


def restarts(current: list[Frame], f: Frame) -> bool:
    """Whether frame ``f`` starts a new exposure sequence after the bracket ``current``:

    - its exposure time repeats one of the bracket (within :data:`SAME_SETTING_STOPS`,
      the rounding of recorded times) other than the previous frame's (repeating the
      previous frame's time is a burst, which merges); or
    - the bracket so far is an ascending sequence of at least :data:`RESTART_MIN_FRAMES`
      frames and ``f`` falls back from its last frame by :data:`RESTART_FALL_STOPS` or
      more (AEB restarting, even when the new sequence's times differ slightly from the
      last one's).  Centre-out orders (0, -, +, --, ++) never ascend from their start, so
      their falls do not split them."""
    t, prev = f.exposure_time, current[-1].exposure_time
    if t is None:
        return False
    if not _same_time(t, prev) and any(_same_time(t, g.exposure_time) for g in current[:-1]):
        return True
    times = [g.exposure_time for g in current]
    if len(times) < RESTART_MIN_FRAMES or any(x is None for x in times):
        return False
    ascending = all(np.log2(b / a) > SAME_SETTING_STOPS for a, b in zip(times, times[1:]))
    return ascending and np.log2(prev / t) >= RESTART_FALL_STOPS - SAME_SETTING_STOPS


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
    """The brackets of the folder, each ``{"frames": [...], "output": ...}``; unreadable
    files are reported as their own failed entries (``"error"``)."""
    frames, bad = [], []
    paths = list_frames(opts.folder)
    if not paths:
        raise HdrMergeError(f"{opts.folder}: no frames to merge in this folder")
    for p in paths:
        p = str(Path(p).resolve())  # absolute: cluster workers do not share our working directory
        try:
            frames.append(read_frame(p))
        except HdrMergeError as exc:
            log.error("%s", exc)
            bad.append({"frames": [p], "output": None, "status": "failed", "error": str(exc)})
    out, taken = [], set()
    outdir = Path(opts.outdir).resolve()
    for group in group_brackets(frames, opts.gap):
        first = Path(group[0].path)
        name = first.stem if first.stem not in taken else f"{first.stem}_{first.suffix.lstrip('.').lower()}"
        k = 2
        while name in taken:  # unique output names: never two brackets on one file
            name, k = f"{first.stem}_{k}", k + 1
        taken.add(name)
        output = outdir / (name + ".exr")
        entry = {"frames": [f.path for f in group], "output": str(output), "status": "planned"}
        if opts.skip_existing and output.exists() and all(
                output.stat().st_mtime >= os.stat(f.path).st_mtime for f in group):
            entry["status"] = "skipped"
        out.append(entry)
    return out + bad


def merge_one(paths: list[str], opts: MergeOptions, profile_text: str | None = None,
              started: float | None = None) -> dict:
    """Merge one bracket; never raises for a bad bracket: returns ``{"status": "failed",
    "error": ...}`` instead.  ``profile_text``: the --profile JSON, sent once to a cluster's
    workers (their file systems may not hold it).  ``started``: the batch's start time on a
    cluster, where a task may run again after its worker died: outputs this batch already
    wrote for it (the EXR and its profile, both newer than ``started``) count as done."""
    profile_out = Path(opts.profile_out) if opts.profile_out else default_profile_path(Path(opts.output))
    if started is not None and all(p.exists() and p.stat().st_mtime >= started for p in (opts.output, profile_out)):
        return {"status": "merged", "summary": {"output": str(opts.output), "profile": str(profile_out),
                                                "retried": True}}
    try:
        if profile_text is not None:
            with tempfile.TemporaryDirectory() as tmp:
                profile = Path(tmp) / "profile.json"
                profile.write_text(profile_text, encoding="utf-8")
                return {"status": "merged", "summary": merge(paths, dataclasses.replace(opts, profile=str(profile)))}
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
    profile_text = Path(opts.merge.profile).read_text(encoding="utf-8") if opts.merge.profile else None
    jobs = [(e, dataclasses.replace(opts.merge, output=Path(e["output"]), profile_out=None)) for e in todo]
    client = _connect(opts.scheduler) if opts.scheduler and jobs else None  # before anything is created
    if todo:  # nothing to write: no output folder either
        opts.outdir.mkdir(parents=True, exist_ok=True)
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
    """One line per bracket for the terminal (the --dry-run listing)."""
    lines = []
    for e in summary["brackets"]:
        names = ", ".join(Path(p).name for p in e["frames"])
        target = e["output"] or "-"
        lines.append(f"{e['status']:8} {target}  <- {names}" + (f"  ({e['error']})" if e.get("error") else ""))
    return "\n".join(lines)
