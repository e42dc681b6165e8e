"""benchmarks/paper/table2.py (Tables II and III): runs on a tiny setting, in the paper's layout."""

import json
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent
# The tables live in benchmarks/paper/: import them from the repository root.
sys.path.insert(0, str(ROOT))


def test_table_layouts():
    from benchmarks.paper.table2 import format_table

    rows = [{"task": t, "particles": n, "max_pushes": None, "dimension": 2,
             "runtime_mean_s": n / 10, "runtime_std_s": 0.5} for t in ("billiards", "pushing")
            for n in (100, 200)]
    text = format_table(2, rows).splitlines()
    assert text[0] == "RUNTIME OF STAMP VARYING THE NUMBER OF PARTICLES"
    assert text[1].split() == ["Particle", "Count", "billiards", "(s)", "pushing", "(s)"]
    assert text[2].split() == ["100", "10.0", "±", "0.5", "10.0", "±", "0.5"]
    rows = [{"task": "pushing", "particles": 64, "max_pushes": k, "dimension": 7 * k,
             "runtime_mean_s": 100.0 + k, "runtime_std_s": 1.0} for k in (1, 2)]
    text = format_table(3, rows).splitlines()
    assert text[2].split() == ["1", "7", "101.0", "±", "1.0"]
    assert text[3].split() == ["2", "14", "102.0", "±", "1.0"]


@pytest.mark.slow
def test_table2_runs_on_a_tiny_setting(tmp_path):
    saved = tmp_path / "table2.json"
    proc = subprocess.run(
        [sys.executable, "-m", "benchmarks.paper.table2", "--tasks", "billiards", "--particles",
         "8", "16", "--seeds", "2", "--devices", "1", "--set", "stamp.svgd_max_iters=3", "--set",
         "stamp.sgd_max_iters=3", "--set", "screen.candidates=1", "--save", str(saved), "--json"],
        capture_output=True, text=True, timeout=1500, cwd=ROOT)
    assert proc.returncode == 0, proc.stderr[-3000:]
    out = json.loads(proc.stdout.strip().splitlines()[-1])
    # --save wrote the rows after each, the last time with every row
    assert json.loads(saved.read_text()) == out
    assert out["table"] == 2 and out["devices"] == 1 and out["seeds"] == 2
    assert [r["particles"] for r in out["rows"]] == [8, 16]
    for r in out["rows"]:
        assert len(r["runtime_s"]) == 2 and r["runtime_mean_s"] > 0
        assert r["dimension"] == 2 and r["task"] == "billiards"
