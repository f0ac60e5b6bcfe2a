"""The output the docs show is the output users get: the quickstart's stress run, printed in
``docs/quickstart.md``, is re-run and compared line by line."""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np
import pytest

from counterscene_env.cli import main

pytestmark = [pytest.mark.slow, pytest.mark.usefixtures("one_torch_thread")]

QUICKSTART = Path(__file__).resolve().parents[1] / "docs" / "quickstart.md"
NUMBER = re.compile(r"-?\d+(?:\.\d+)?(?:e-?\d+)?")


def documented_output() -> list[str]:
    """The lines of the quickstart's ``text`` block (the README command's printout)."""
    block = QUICKSTART.read_text().split("```text\n", 1)[1].split("```", 1)[0]
    return block.strip().splitlines()


def test_the_quickstart_prints_what_the_docs_show(capsys):
    code = main(["stress", "--scenario", "intersection", "--episodes", "4"])
    assert code == 0
    printed = capsys.readouterr().out.strip().splitlines()
    documented = documented_output()
    assert len(printed) == len(documented)
    # The last line is compute time; every other line is a result of the same scenes and
    # seeds. Rates are exact; ADE, FDE, TTC and clearance may differ in the last digits on
    # another CPU (float rounding in the network's matrix products).
    for got, want in zip(printed[:-1], documented[:-1], strict=True):
        assert NUMBER.sub("#", got) == NUMBER.sub("#", want), (got, want)
        np.testing.assert_allclose(
            [float(x) for x in NUMBER.findall(got)],
            [float(x) for x in NUMBER.findall(want)],
            rtol=0.01,
            atol=0.005,
            err_msg=f"docs/quickstart.md shows {want!r}, the command printed {got!r}",
        )
    assert printed[-1].endswith("s per replan")
