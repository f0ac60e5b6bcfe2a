"""Reports of stress runs: what a planner author reads after ``counterscene stress --out DIR``
(docs/reports.md).

- ``write.py``: :func:`write_report`, a run directory's ``report.html``, ``report.md``,
  ``plots/``, ``videos/`` and ``command.txt``;
- ``compare.py``: :func:`compare_runs`, several runs side by side with paired tests
  (``counterscene compare``);
- ``rundir.py``: a run directory read back; ``stats.py``: intervals and paired tests;
  ``tables.py``: a run's numbers with intervals; ``ranking.py``: the worst episodes;
  ``plots.py``: the PNGs; ``replay.py``: an episode re-simulated from its seeds;
  ``video.py``: its frames and video files; ``command.py``: the rerun command line;
  ``document.py``, ``markdown.py``, ``html.py``: a report's blocks and their two renderings;
  ``run_report.py``: the content of a run's report.

The package sits above ``stress`` (it reads its records and replays its episodes) and below
the CLI.
"""

__all__ = ["compare_runs", "load_run", "write_report"]

#: Where each name lives; imported on first use (matplotlib and torch load only when needed).
_FROM = {"write_report": "write", "compare_runs": "compare", "load_run": "rundir"}


def __getattr__(name: str):
    if name not in _FROM:
        raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
    import importlib

    return getattr(importlib.import_module(f"{__name__}.{_FROM[name]}"), name)
