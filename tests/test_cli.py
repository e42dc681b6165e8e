"""The command line: one-line errors with exit status 2, JSON output."""

import json

import pytest

from mjstamp.cli import main


@pytest.mark.parametrize(
    "argv, expected",
    [
        (["check", "nope"], "unknown scene 'nope'; valid: billiards, pushing"),
        (["check", "/nonexistent/scene.xml"], "/nonexistent/scene.xml: MJCF file not found"),
        (["check", "billiards", "--particles", "0"], "--particles=0 must be in 1..65536"),
    ],
)
def test_bad_input_is_one_line_and_status_2(argv, expected, capsys):
    assert main(argv) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert err == [f"mjstamp: error: {expected}"]


def test_malformed_mjcf_file(tmp_path, capsys):
    path = tmp_path / "broken.xml"
    path.write_text("<mujoco><worldbody>")
    assert main(["check", str(path)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and str(path) in err[0] and "XML" in err[0]


@pytest.mark.slow
def test_check_json_is_the_only_stdout(capsys):
    assert main(["check", "billiards", "--particles", "4", "--json", "--quiet"]) == 0
    report = json.loads(capsys.readouterr().out)
    assert report["scene"] == "billiards" and report["particles"] == 4
    assert report["nonfinite"] == 0
    for key in ("nonfinite_fraction", "rel_err_median", "rel_err_p95", "us_per_particle_step"):
        assert key in report


@pytest.mark.slow
def test_check_text_report_of_a_healthy_scene(tmp_path, capsys, tiny_xml):
    """The text report of a calibrated, faithful scene (judged by the tolerance, no chaos)."""
    path = tmp_path / "tiny.xml"
    path.write_text(tiny_xml())
    assert main(["check", str(path), "--particles", "4", "--horizon", "20", "--quiet"]) == 0
    out = capsys.readouterr().out
    assert "calibrated       scene 'tiny':" in out and out.rstrip().endswith("healthy")
    assert "physics          MJX vs MuJoCo C (scene's own solver): divergence median" in out


def test_coverage_line_says_what_it_measured(capsys):
    """Feasible task plans over the share threshold, and found of all the sweep holds."""
    from mjstamp import modes
    from mjstamp.cli.solve import print_table

    sweep = {"modes": [{"task_plan": "a", "share": 0.5}, {"task_plan": "b", "share": 0.2},
                       {"task_plan": "c", "share": 1e-4}, {"task_plan": "d", "share": 2e-4}],
             "grid": 10}
    detail = modes.coverage(["a", "c"], sweep)
    assert (detail["swept"], detail["swept_found"], detail["missed"]) == (4, 2, ["b"])
    print_table({"task": "t", "plans": [], "task_plans": [], "particles": 2, "wall_time_s": 1.0,
                 "returned_plans": 2, "verified_fraction": 1.0, "declaration": {"symbols": []},
                 "distinct_verified_task_plans": 2, "coverage": detail["coverage"],
                 "coverage_detail": detail})
    last = capsys.readouterr().out.strip().splitlines()[-1]
    assert last == ("coverage: 50% of the 2 task plans occupying >= 0.1% of the box "
                    "(missed: b); found 2 of all the sweep's 4")
