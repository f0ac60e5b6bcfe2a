"""The research tools whose output other figures rest on (``tools/``)."""

from __future__ import annotations

import runpy
from pathlib import Path

import numpy as np
import pytest
from conftest import make_scene

ROOT = Path(__file__).resolve().parents[1]


def _run_tool(name: str, argv: list[str], monkeypatch) -> None:
    monkeypatch.setattr("sys.argv", [f"tools/{name}.py", *argv])
    runpy.run_path(str(ROOT / "tools" / f"{name}.py"), run_name="__main__")


def test_ngsim_split_holds_out_whole_map_sections_and_copies_nothing(tmp_path, monkeypatch):
    """The held-out NGSIM figures are honest only if no map section (whose files share
    vehicles) has files on both sides, and the split links the files rather than copying
    shared data."""
    src = tmp_path / "src"
    src.mkdir()
    names = [
        "USA_US101-5_1_T-1.xml",  # a held-out US-101 section ...
        "USA_US101-5_2_T-1.xml",  # ... with every one of its files
        "USA_US101-50_1_T-1.xml",  # 50 is not 5: a training section
        "USA_US101-1_1_S-1.xml",
        "USA_Peach-3_1_T-1.xml",
        "USA_Lanker-2_4_T-1.xml",
    ]
    for n in names:
        (src / n).write_text("<commonRoad/>")
    out = tmp_path / "split"
    _run_tool("ngsim_split", [str(src), str(out)], monkeypatch)
    heldout = {p.name for p in (out / "heldout").iterdir()}
    train = {p.name for p in (out / "train").iterdir()}
    assert heldout == {"USA_US101-5_1_T-1.xml", "USA_US101-5_2_T-1.xml", "USA_Peach-3_1_T-1.xml"}
    assert train == set(names) - heldout
    assert all(p.is_symlink() for p in out.rglob("*.xml"))
    # Rerunning is harmless (the links exist already).
    _run_tool("ngsim_split", [str(src), str(out)], monkeypatch)
    assert {p.name for p in (out / "heldout").iterdir()} == heldout


def test_ngsim_split_refuses_a_name_it_cannot_place_and_writes_nothing(tmp_path, monkeypatch):
    (tmp_path / "USA_US101-5_1_T-1.xml").write_text("<commonRoad/>")  # sorted first, placeable
    (tmp_path / "scenario.xml").write_text("<commonRoad/>")
    with pytest.raises(SystemExit, match=r"scenario\.xml"):
        _run_tool("ngsim_split", [str(tmp_path), str(tmp_path / "out")], monkeypatch)
    assert not (tmp_path / "out").exists()


def _selection_row(folder: Path, hits: list[int], tiers: list[int | None]) -> None:
    """A paper-tables row of episodes that hit their adversary (1) or not (0) at every second;
    ``None`` tiers are episodes with no adversary."""
    import json

    folder.mkdir(parents=True)
    (folder / "run.json").write_text(json.dumps({"scenario": "intersection", "seed": 0}))
    lines = []
    for i, (hit, tier) in enumerate(zip(hits, tiers, strict=True)):
        per = {str(s): {"ADE": 1.0, "CR_adv": float(hit) if tier else None} for s in range(1, 11)}
        record = {"per_second": per, "adversary_tier": tier, "cr_ego_adversary": hit}
        record |= {"episode": i, "seed": i, "scenario_id": f"s{i}", "cr": hit, "hbr_ego": 0}
        record |= {"orr": 0, "min_ttc": 1.0, "min_clearance_adversary": 1.0}
        lines.append(json.dumps({**record, "adversary_id": "a" if tier else None}))
    (folder / "episodes.jsonl").write_text("\n".join(lines) + "\n")


def test_selection_horizon_mined_keeps_the_causal_rows_valid_mining_cases(
    tmp_path, monkeypatch, capsys
):
    """``--mined``: every row on the episodes where the causal selection found a conflict; the
    baseline's hit where causal had no adversary leaves the comparison."""
    _selection_row(tmp_path / "counterscene", [1, 1, 0, 0], [1, 2, 1, None])
    _selection_row(tmp_path / "ttc", [1, 0, 0, 1], [1, 1, 1, 1])
    _run_tool("selection_horizon", [str(tmp_path)], monkeypatch)
    assert "causal / best baseline (ttc): 1.00x" in capsys.readouterr().out  # 2 hits each
    _run_tool("selection_horizon", [str(tmp_path), "--mined"], monkeypatch)
    out = capsys.readouterr().out
    assert "3 of 4 episodes are valid mining cases" in out
    assert "causal / best baseline (ttc): 2.00x" in out  # 2 hits against 1


def test_early_speed_track_alone_scores_the_continued_acceleration_against_the_log():
    """The track-alone baselines behind the hypotheses table's row on recent accelerations:
    on a car that keeps accelerating, continuing its recent acceleration beats constant
    velocity, and on a car that holds its speed both are exact."""
    tool = runpy.run_path(str(ROOT / "tools" / "early_speed.py"), run_name="early_speed")
    t = np.arange(80) * 0.1
    speeds = np.stack([np.full(80, 10.0), 5.0 + 1.0 * t])  # held, and +1 m/s^2 throughout
    x = np.stack([10.0 * t, 5.0 * t + 0.5 * t**2])
    scene = make_scene(np.stack([x, np.stack([np.zeros(80), np.full(80, 4.0)])], -1), speeds=speeds)
    rows = tool["track_alone"]([scene], [(0, 30), (0, 40)], [0.5, 1.0])
    assert len(rows["recent"]) == 4  # two cars, two windows each
    np.testing.assert_allclose(rows["recent"], [0.0, 1.0, 0.0, 1.0], atol=1e-9)
    np.testing.assert_allclose(rows["next"], rows["recent"], atol=1e-9)
    held, accelerating = slice(0, None, 2), slice(1, None, 2)
    for tau in (0.0, 0.5, 1.0, "positions"):
        assert rows[tau][held].max() < 0.02  # the held speed: every baseline on the log
    cv, continued = rows[0.0][accelerating].mean(), rows[1.0][accelerating].mean()
    assert continued < 0.7 * cv  # a continuation of 1 m/s^2 over 1 s closes much of the gap
    # A window without 3 s of logged future is not scored.
    assert len(tool["track_alone"]([scene], [(0, 60)], [0.5])["recent"]) == 0
