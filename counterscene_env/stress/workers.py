"""``counterscene stress --workers N``: a stress run's batches in N local processes.

The parent forms the batches exactly as the serial run does (:func:`~.episodes.chunks`: the
same scenes, seeds and batch boundaries) and hands whole batches to the workers, because a
batched world-model call's floating-point results can depend on the batch's composition.
Each worker is a fresh (``spawn``) process with one torch thread that loads the model
itself and runs batches with the serial run's runner (:class:`~.episodes.BatchRunner` or
:class:`~.episodes.PolicyRunner`). Finished batches are recorded in episode order (a batch
that finishes early waits for the ones before it), so ``episodes.jsonl`` and the records are
those of the serial run, and a stopped parallel run resumes like a serial one.

Ctrl-C reaches the parent only (the workers ignore SIGINT): it stops the workers and raises
``KeyboardInterrupt`` with every batch finished before it on disk.
"""

from __future__ import annotations

import collections
import multiprocessing as mp
import pickle
import queue
import signal
import traceback
from collections.abc import Callable

from counterscene_env.planners import Planner
from counterscene_env.stress.config import StressConfig
from counterscene_env.stress.episodes import Progress, chunks, first_to_run, make_runner
from counterscene_env.stress.log import EpisodeLog

#: Batches handed out per worker ahead of the results: enough to keep every worker busy while
#: the parent records a result, few enough that a stop wastes little and scenes are drawn
#: lazily.
BATCHES_AHEAD = 2
#: Errors a worker hands back as they are (bad input the command reports in one line);
#: any other failure comes back as its traceback.
USER_ERRORS = (ValueError, TypeError, FileNotFoundError)
#: How often the parent checks that its workers are alive while it waits [s].
POLL_SECONDS = 0.5
#: How long an idle worker may take to exit after the last batch [s].
STOP_SECONDS = 10.0


def run_parallel(
    config: StressConfig,
    workers: int,
    model: str = "default",
    env_config: dict | None = None,
    planner_factory: Callable[[], Planner] | None = None,
    progress: bool = True,
    log: EpisodeLog | None = None,
) -> list[dict]:
    """Run every episode in ``workers`` processes; the records of the serial run
    (:func:`~.episodes.run_episodes`, or :func:`~.episodes.run_policy_episodes` for an sb3
    planner) for the same config, in order.

    Args:
        config: the run.
        workers: processes (>= 1); never more are started than batches remain.
        model: the world model's directory (``"default"``: the shipped one); each worker
            loads it.
        env_config: sb3 planners: env-config keys on top of the policy's sidecar.
        planner_factory: a fresh planner per episode (default ``make_planner(config.planner)``);
            it is sent to the workers, so it must be picklable: a class or a module-level
            function, not a lambda.
        progress: show a progress bar with ETA.
        log: as in :func:`~.episodes.run_episodes`.

    Raises:
        RuntimeError: a worker failed (the message holds its traceback) or died.
    """
    if workers < 1:
        raise ValueError(f"--workers must be >= 1, got {workers}")
    tally = Progress(config, log, progress)
    todo = chunks(config, tally.records)
    spec = (config, model, env_config, planner_factory)
    ctx = mp.get_context("spawn")
    tasks, results = ctx.Queue(), ctx.Queue()
    start = first_to_run(config, tally.records)
    remaining = -(-(config.episodes - start) // config.batch)  # batches
    procs = [
        ctx.Process(target=_serve, args=(spec, tasks, results), name=f"stress-worker-{k}")
        for k in range(min(workers, remaining))
    ]
    finished = False
    try:
        _start(procs)
        _collect(todo, tasks, results, procs, tally)
        finished = True
    finally:
        tally.close()
        _stop(procs, tasks, wait=finished)
    return tally.records


def _start(procs) -> None:
    """Start the workers with SIGINT ignored, which they inherit: a Ctrl-C while they import
    is the parent's to handle, not a traceback from each worker."""
    handler = signal.signal(signal.SIGINT, signal.SIG_IGN)
    try:
        for p in procs:
            p.daemon = True  # never outlives the parent
            p.start()
    finally:
        signal.signal(signal.SIGINT, handler)


def _collect(todo, tasks, results, procs, tally: Progress) -> None:
    """Hand out batches and record their results in episode order until none remain."""
    sent: collections.deque[int] = collections.deque()  # first episodes, in order
    done: dict[int, list[dict]] = {}  # finished, not yet recorded (an earlier one runs)
    ahead = BATCHES_AHEAD * len(procs)

    def feed() -> None:
        while len(sent) - len(done) < ahead:  # batches queued or running
            nxt = next(todo, None)
            if nxt is None:
                return
            # Pickled here, not in the queue's feeder thread: a batch that cannot travel
            # fails the run at once instead of leaving it waiting for a result forever.
            tasks.put(pickle.dumps(nxt))
            sent.append(nxt[0])

    feed()
    while sent:
        first, records = _next_result(results, procs)
        done[first] = records
        while sent and sent[0] in done:
            tally.add(done.pop(sent.popleft()))
        feed()


def _next_result(results, procs) -> tuple[int, list[dict]]:
    """The next finished batch from any worker; raises if a worker failed or died."""
    while True:
        try:
            first, records, error = results.get(timeout=POLL_SECONDS)
        except queue.Empty:
            dead = [p for p in procs if p.exitcode is not None]
            if not dead:
                continue
            try:  # a failing worker sends its traceback before it exits
                first, records, error = results.get(timeout=POLL_SECONDS)
            except queue.Empty:
                p = dead[0]
                raise RuntimeError(
                    f"stress worker {p.name} stopped (exit code {p.exitcode}) without a result"
                ) from None
        if error is not None:
            exc, text = error
            if isinstance(exc, USER_ERRORS):
                raise exc  # bad input (e.g. a policy whose spaces do not fit), as serial
            raise RuntimeError(f"stress worker failed:\n{text}")
        return first, records


def _stop(procs, tasks, wait: bool) -> None:
    """End the workers: after a finished run (``wait``) on a sentinel each, as they are idle;
    after a stop or failure at once, since their batches are not wanted any more."""
    # Batches never taken stay in the queue: do not wait to flush them at exit. First, so
    # that a second Ctrl-C during the joins below cannot leave the exit waiting on it.
    tasks.cancel_join_thread()
    if wait:
        for _ in procs:
            tasks.put(None)
    for p in procs:
        if p.pid is None:  # never started
            continue
        p.join(timeout=STOP_SECONDS if wait else 0)
        if p.is_alive():
            p.terminate()
            p.join()
    tasks.close()


def _serve(spec: tuple, tasks, results) -> None:
    """A worker: build the runner once, then run each batch it is sent until the sentinel."""
    import torch

    signal.signal(signal.SIGINT, signal.SIG_IGN)  # the parent stops the workers
    torch.set_num_threads(1)  # one thread per process: N workers share N cores
    try:
        runner = make_runner(*spec)
    except Exception as exc:
        results.put((None, None, _failure(exc)))
        return
    try:
        while (task := tasks.get()) is not None:
            first, scenes = pickle.loads(task)  # the parent's own batch (_collect)
            try:
                results.put((first, runner(first, scenes), None))
            except Exception as exc:
                results.put((first, None, _failure(exc)))
                return
    finally:
        runner.close()


def _failure(exc: Exception) -> tuple[Exception | None, str]:
    """A worker's exception for the parent: itself when it is bad input the parent reports
    as the serial run would, and its traceback."""
    text = traceback.format_exc()
    if not isinstance(exc, USER_ERRORS):
        return None, text
    try:
        pickle.dumps(exc)
    except Exception:  # an exception that cannot travel: its traceback does
        return None, text
    return exc, text
