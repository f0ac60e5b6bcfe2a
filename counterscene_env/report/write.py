"""Write a stress run's report into its directory (:func:`write_report`)."""

from __future__ import annotations

import importlib.util
import os
import shlex
import shutil
import tempfile
from collections.abc import Sequence
from pathlib import Path

from counterscene_env.config import check_int
from counterscene_env.report import html, markdown, ranking
from counterscene_env.report.command import command_text, stress_argv
from counterscene_env.report.plots import PLOTS, REPORT_PLOTS, histograms, per_second_plots
from counterscene_env.report.run_report import EpisodeVideo, document
from counterscene_env.report.rundir import Run, load_run
from counterscene_env.report.tables import per_second_table

#: Where the videos go, relative to the run directory.
VIDEOS = Path("videos")

VIDEO_EXTRA = 'pip install "counterscene-env[video]"'


def write_report(directory: str | os.PathLike, videos: int = 3, progress: bool = True) -> Path:
    """Write the report of the stress run in ``directory`` (``counterscene stress --out``).

    Writes, beside ``run.json``, ``episodes.jsonl`` and ``metrics.json``:

    - ``report.html`` (self-contained: plots embedded, no script or remote address) and
      ``report.md``: what was run, the paper's table and the whole-episode metrics with 95 %
      intervals, the plots, the worst episodes ranked by severity with links to their videos;
    - ``plots/*.png``: CR and HBR, ADE and FDE against the horizon second; histograms of min
      TTC, min clearance to the adversary (and the ego's peak deceleration where the records
      have it);
    - ``videos/episode_NNNN.mp4`` and ``.gif``: the ``videos`` worst episodes, re-simulated
      from their seeds (needs the ``video`` extra; the report says when videos could not be
      made, and why);
    - ``command.txt``: the ``counterscene stress`` command line that reruns the run.

    A run stopped midway (no ``metrics.json`` yet) gets a report of its finished episodes.
    The files are made elsewhere and moved in at the end: a report that fails (or is
    stopped) on the way leaves the directory as it was.

    Args:
        directory: the run directory.
        videos: how many of the worst episodes to re-simulate and film (0: none).
        progress: show a progress bar (with ETA) while re-simulating.

    Returns:
        The path of ``report.html``.

    Raises:
        FileNotFoundError, ValueError: not a readable run directory (``report.rundir.load_run``;
            the message names the file and the field).
        TypeError, ValueError: ``videos`` not an int >= 0.
    """
    videos = check_int("videos", videos, ge=0)
    run = load_run(directory)
    root = run.directory
    # Everything is made in a scratch directory and moved in only once all of it stands:
    # a run the report refuses (a bad run.json, a record no table can read), a crash or a
    # Ctrl-C while filming leaves the run directory as it was, an earlier report included.
    command = command_text(run)
    with tempfile.TemporaryDirectory(prefix="counterscene-report-") as scratch:
        stage = Path(scratch)
        figs = per_second_plots(per_second_table(run.records), stage)
        hist_figs, notes = histograms(run.records, stage)
        worst = ranking.worst_episodes(run.records, videos)
        made, video_note = _videos(run, worst, stage, progress) if worst else ({}, _NO_VIDEOS)
        blocks = document(
            run, shlex.join(stress_argv(run)), [*figs, *hist_figs], notes, made, video_note
        )
        (stage / "command.txt").write_text(command)
        (stage / "report.md").write_text(markdown.render(blocks))
        # Last: the page embeds the plots, so it is written once they are.
        (stage / "report.html").write_text(html.render(blocks, stage, f"Stress report: {run.name}"))
        _move_in(stage, root)
    kept = {f.path for f in [*figs, *hist_figs]}
    kept |= {p for v in made.values() for p in (v.mp4, v.gif) if p is not None}
    _drop_stale(root, kept)
    return root / "report.html"


#: The report's own files, moved into the run directory after its plots and videos, so that
#: a page is never in place before what it shows.
_PAGES = ("command.txt", "report.md", "report.html")


def _move_in(stage: Path, root: Path) -> None:
    """Move every file of ``stage`` to the same place under ``root`` (replacing an earlier
    report's), the pages last.

    Raises:
        ValueError: a file's place under ``root`` is taken by a directory, or a folder's
            by a file (checked before anything moves).
    """
    files = sorted(p.relative_to(stage) for p in stage.rglob("*") if p.is_file())
    files.sort(key=lambda rel: str(rel) in _PAGES)  # stable: plots and videos first
    for rel in files:
        target = root / rel
        if target.is_dir():
            raise ValueError(f"{target} is a directory: the report cannot write its file there")
        for parent in list(rel.parents)[:-1]:
            if (root / parent).is_file():
                raise ValueError(f"{root / parent} is a file: the report needs a folder there")
    for rel in files:
        (root / rel).parent.mkdir(parents=True, exist_ok=True)
        shutil.move(stage / rel, root / rel)


def _drop_stale(root: Path, kept: set[Path]) -> None:
    """Remove what an earlier report of this run wrote and this one did not (videos of
    episodes no longer among the worst, a histogram the records no longer support), so the
    directory holds this report's files only. Other files are left alone."""
    stale = [*root.glob(f"{VIDEOS}/episode_*.mp4"), *root.glob(f"{VIDEOS}/episode_*.gif")]
    stale += [root / PLOTS / name for name in REPORT_PLOTS]
    for path in stale:
        if path.relative_to(root) not in kept:
            path.unlink(missing_ok=True)


_NO_VIDEOS = "No videos were asked for (counterscene report DIR --videos K makes K)."


def _videos(
    run: Run, worst: Sequence[dict], stage: Path, progress: bool
) -> tuple[dict[int, EpisodeVideo], str | None]:
    """Replay and film the ``worst`` episodes into ``stage/videos/``: ``{episode:
    EpisodeVideo}`` (paths relative to ``stage``) and a note on the videos as a whole (None
    when every video was made)."""
    from counterscene_env.report.replay import can_replay

    reason = can_replay(run)
    if reason:
        return {}, f"No videos: {reason}."
    if importlib.util.find_spec("imageio") is None:
        return {}, f"No videos: they need the video extra, {VIDEO_EXTRA}."
    from tqdm.auto import tqdm

    from counterscene_env.report.replay import group_by_batch, replay_batch
    from counterscene_env.report.video import write_videos
    from counterscene_env.world_model.checkpoint import CheckpointError, load_model

    model_name = str(run.identity.get("model", "default"))
    try:
        model = load_model(model_name)
    except CheckpointError as exc:
        return {}, f"No videos: the run's world model {model_name!r} does not load ({exc})."
    out: dict[int, EpisodeVideo] = {}
    bar = tqdm(total=len(worst), desc="videos", unit="ep", disable=not progress)
    for batch, episodes in group_by_batch(run, [r["episode"] for r in worst]).items():
        try:
            replays = replay_batch(model, run, batch, episodes)
        except (ValueError, FileNotFoundError) as exc:
            out.update({e: EpisodeVideo(problem=str(exc)) for e in episodes})
            bar.update(len(episodes))
            continue
        for rep in replays:
            stem = f"episode_{rep.record['episode']:04d}"
            files = write_videos(rep, stage / VIDEOS, stem)
            out[rep.record["episode"]] = EpisodeVideo(
                mp4=VIDEOS / f"{stem}.mp4" if isinstance(files["mp4"], Path) else None,
                gif=VIDEOS / f"{stem}.gif",
                mismatches=rep.mismatches,
            )
            bar.update(1)
    bar.close()
    missing_mp4 = any(v.gif and not v.mp4 for v in out.values())
    note = f"GIF only: MP4 needs imageio-ffmpeg, {VIDEO_EXTRA}." if missing_mp4 else None
    return out, note
