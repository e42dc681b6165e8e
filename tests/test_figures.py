"""Figures of a solve (mjstamp.figures): files, readability, and what they draw."""

import dataclasses
import subprocess
import sys
import types

import numpy as np
import pytest
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.collections import PathCollection
from matplotlib.image import imread

from mjstamp import figures, geometry, solve, verify
from mjstamp.errors import MjstampError

CONFIG = {
    "particles": 8,
    "stamp.svgd_learning_rate": 0.1,
    "stamp.sgd_learning_rate": 0.05,
    "stamp.svgd_max_iters": 4,
    "stamp.sgd_max_iters": 4,
    "stamp.min_iters": 2,
}


def figures_task(tiny_task):
    """The conftest's tiny task with a turned wall, a large goal and drawing hints."""
    # Generous radius: with 8 particles and 8 iterations some plans must verify.
    task = tiny_task(horizon=30, turn=10, goal_size=0.1, radius=0.6)
    task.display(trace=["puck"], force=[("puck", "wall")])
    return task


@pytest.fixture(scope="module")
def result(tiny_task):
    """A whole solve of the tiny task (about 15 s with a warm compilation cache)."""
    return solve(figures_task(tiny_task), CONFIG, seed=0, progress=False)


def _is_readable(fig):
    """Every axes that draws data has a title, and every title fits inside the figure."""
    drawn = [ax for ax in fig.axes if ax.get_label() != "<colorbar>" and ax.axison]
    assert drawn
    canvas = FigureCanvasAgg(fig)
    canvas.draw()
    titles = [ax.title for ax in drawn] + [t for t in fig.texts if t.get_text()]
    for ax in drawn:
        assert ax.get_title(), ax
    for title in titles:
        box = title.get_window_extent(canvas.get_renderer())
        assert 0 <= box.x0 and box.x1 <= fig.bbox.width, (title.get_text(), box)
    return drawn


@pytest.mark.slow
def test_save_figures_writes_valid_non_blank_pngs(result, tmp_path):
    written = figures.save_figures(result, tmp_path, grid=12, progress=False)
    names = [p.name for p in written]
    assert names == ["plans_histogram.png", "plans_topdown.png", "loss.png",
                     "svgd_diagnostics.png", "robustness.png", "landscape.png"]
    for path in written:
        assert path.is_file()
        assert path.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
        image = imread(path)
        height, width = image.shape[:2]
        assert 500 <= width <= 4000 and 300 <= height <= 3000, (path.name, image.shape)
        # Not blank: a figure of text, lines and patches varies well beyond 1e-3.
        assert image[..., :3].std() > 0.05, path.name
    # Atomic writes leave no temporary siblings behind.
    assert sorted(p.name for p in tmp_path.iterdir()) == sorted(names)


@pytest.mark.slow
def test_robustness_figure_has_a_row_per_scored_task_plan_with_its_median(result):
    fig = figures.robustness_figure(result)
    ax = _is_readable(fig)[0]
    assert "nominal planning; " in ax.get_title()  # the fixture's solve is not robust
    success = result.robustness["success"]
    plans_of = figures.particle_plans(result)
    scored = sorted({p for p, s in zip(plans_of, success, strict=True) if np.isfinite(s)})
    assert scored and [t.get_text() for t in ax.get_yticklabels()] == scored
    medians = [line.get_xdata()[0] for line in ax.get_lines()]
    assert medians == pytest.approx(
        [np.median(success[(plans_of == p) & np.isfinite(success)]) for p in scored])


@pytest.mark.slow
def test_no_landscape_when_not_asked(result, tmp_path):
    written = figures.save_figures(result, tmp_path, landscape=False)
    assert "landscape.png" not in [p.name for p in written]


@pytest.mark.slow
def test_histogram_counts_verified_and_failed(result):
    fig = figures.histogram_figure(result)
    (ax,) = _is_readable(fig)
    assert "task plan" in ax.get_xlabel() and "wall" in ax.get_xlabel()
    assert ax.get_ylabel() == "plans"
    assert ax.get_legend() is not None
    labels = [t.get_text() for t in ax.get_xticklabels()]
    assert labels == [r["task_plan"] for r in result.rows]
    heights = [p.get_height() for p in ax.containers[0]]
    assert heights == [r["verified"] for r in result.rows]
    assert sum(heights) == result.verified_mask().sum() > 0


@pytest.mark.slow
def test_loss_figure_shows_both_phases(result):
    fig = figures.loss_figure(result)
    (ax,) = _is_readable(fig)
    assert ax.get_xlabel() == "iteration" and "loss" in ax.get_ylabel()
    legend = [t.get_text() for t in ax.get_legend().get_texts()]
    assert legend == ["mean over particles", "best particle"]
    mean = ax.get_lines()[0].get_ydata()
    np.testing.assert_allclose(mean, -result.diagnostics.logdensity_mean)
    texts = " ".join(t.get_text() for t in ax.texts)
    assert "SVGD" in texts and "SGD" in texts


def _valleys(x):
    """Batched (log density, no aux): a flat plateau with three narrow Gaussian valleys."""
    import jax.numpy as jnp

    centres = jnp.array([[1.0, 1.0], [-1.5, 0.5], [0.5, -1.5]])
    d2 = jnp.sum((x[:, None] - centres[None]) ** 2, -1)
    return 5.0 * jnp.sum(jnp.exp(-d2 / (2 * 0.15**2)), 1) - 5.0, jnp.zeros((len(x), 0))


def test_diagnostics_figure_draws_what_the_steps_recorded(tmp_path):
    """Driving vs repulsive norms, bandwidth, step and near-zero share, both phases named."""
    import jax

    from mjstamp import svgd

    config = svgd.StampConfig(svgd_max_iters=12, sgd_max_iters=8, min_iters=20)
    res = svgd.run_stamp(
        _valleys, lambda k: jax.random.uniform(k, (16, 2), minval=-3, maxval=3), svgd.rbf(),
        config, progress=False,
    )  # fmt: skip
    d = res.diagnostics
    fig = figures.diagnostics_figure(res)
    terms, bands, steps, stalled = _is_readable(fig)
    assert "driving" in terms.get_title() and "repulsive" in terms.get_title()
    assert [ax.get_xlabel() for ax in (steps, stalled)] == ["iteration", "iteration"]
    lines = {line.get_label(): line.get_ydata() for line in terms.get_lines()}
    np.testing.assert_allclose(lines["driving, mean"], d.driving_norm_mean)
    np.testing.assert_allclose(lines["repulsive, median"], d.repulsion_norm_median)
    assert np.all(np.isnan(lines["driving, mean"][12:]))  # SGD has no driving term
    np.testing.assert_allclose(bands.get_lines()[0].get_ydata(), d.bandwidth[:, 0])
    steps_drawn = {line.get_label(): line.get_ydata() for line in steps.get_lines()}
    np.testing.assert_allclose(steps_drawn["mean ‖Δθ_i‖"], d.displacement)
    np.testing.assert_allclose(steps_drawn["mean |Δθ[1]|"], d.displacement_per_coordinate[:, 1])
    np.testing.assert_allclose(stalled.get_lines()[0].get_ydata(), d.near_zero_share)
    np.testing.assert_allclose(stalled.get_lines()[1].get_ydata(), d.self_weight_median)
    # Most particles start on the plateau: the share the figure shows is large.
    assert d.near_zero_share[0] > 0.5
    texts = " ".join(t.get_text() for t in terms.texts)
    assert "SVGD\n12 iterations" in texts and "SGD\n8 iterations" in texts
    figures._save(fig, tmp_path / "d.png")
    assert imread(tmp_path / "d.png")[..., :3].std() > 0.05


@pytest.mark.slow
def test_topdown_one_panel_per_verified_task_plan(result):
    fig = figures.topdown_figure(result)
    panels = _is_readable(fig)
    chosen = figures.best_verified(result)
    assert len(panels) == len(chosen) > 0
    for ax, (plan, i) in zip(panels, chosen, strict=True):
        assert ax.get_title().startswith(plan)
        assert result.verified_mask()[i]
        # Scene patches (floor, wall, goal site, puck at start and end) and the path.
        assert len(ax.patches) >= 5
        path = ax.get_lines()[0].get_xydata()
        np.testing.assert_allclose(path[1:], result.replay.body_pos("puck")[i, :, :2])
    assert any(ax.get_xlabel() == "x [m]" for ax in panels)
    assert panels[0].get_ylabel() == "y [m]"
    legend = [t.get_text() for t in fig.legends[0].get_texts()]
    assert "puck path" in legend and any("force of puck on wall" in t for t in legend)
    # The best plan of each task plan has the lowest cost among its verified plans.
    for plan, i in chosen:
        same = [j for j in np.flatnonzero(result.verified_mask())
                if result.verified.plan[j] == plan]
        assert result.cost[i] == min(result.cost[j] for j in same)


@pytest.mark.slow
def test_landscape_panels_and_colors(result):
    fig = figures.landscape_figure(result, grid=12, progress=False)
    panels = _is_readable(fig)
    assert [ax.get_title().split(" (")[0] for ax in panels] == [
        "initial", "end of SVGD", "end of SGD"]
    assert panels[0].get_xlabel() == "v[0]" and panels[0].get_ylabel() == "v[1]"
    colorbar = [ax for ax in fig.axes if ax.get_label() == "<colorbar>"]
    assert len(colorbar) == 1 and "cost" in colorbar[0].get_ylabel()
    legend = [t.get_text() for t in fig.legends[0].get_texts()]
    plans_found = sorted(set(result.verified.plan[result.verified_mask()]))
    assert legend[:-1] == [f"{p} ({np.sum(figures.particle_plans(result) == p)})"
                           for p in plans_found]
    assert legend[-1].startswith("not returned / failed")
    # Every particle is drawn once per panel, at its θ of that stage.
    for ax, theta in zip(panels, (result.initial_theta, result.svgd_theta, result.theta),
                         strict=True):
        drawn = np.concatenate([c.get_offsets() for c in ax.collections
                                if isinstance(c, PathCollection)])
        assert len(drawn) == len(theta)
        np.testing.assert_allclose(np.sort(drawn[:, 0]), np.sort(theta[:, 0]))


@pytest.mark.slow
def test_a_solve_with_nothing_returned_still_draws(result, tmp_path):
    """No returned plan: a histogram saying so, the closest miss, all particles gray."""
    n = result.theta.shape[0]
    empty = dataclasses.replace(result, returned=np.zeros(n, bool), rows=[])
    (ax,) = _is_readable(figures.histogram_figure(empty))
    assert "no plans returned" in [t.get_text() for t in ax.texts]
    fig = figures.topdown_figure(empty)
    (panel,) = _is_readable(fig)
    assert "failed" in panel.get_title() and "no verified plan" in fig.get_suptitle()
    fig = figures.landscape_figure(empty, grid=4, progress=False)
    legend = [t.get_text() for t in fig.legends[0].get_texts()]
    assert legend == [f"not returned / failed ({n})"]
    assert len(figures.save_figures(empty, tmp_path, grid=4, progress=False)) == 6


@pytest.mark.slow
def test_landscape_cost_equals_the_task_cost(result):
    """The grid is the MJX cost at its points, whatever the batch padding."""
    import jax.numpy as jnp

    task = result.task
    xs, ys, cost = figures.landscape_cost(task, 8, [-2, -1], [2, 1], 5, progress=False)
    assert cost.shape == (5, 5)
    theta = np.array([[xs[3], ys[1]], [xs[0], ys[4]]])
    _, values = task.evaluate(jnp.asarray(theta))
    np.testing.assert_allclose([cost[1, 3], cost[4, 0]], task.cost_total(values), rtol=1e-9)
    with pytest.raises(MjstampError, match="grid=1 must be >= 2"):
        figures.landscape_figure(result, grid=1)


@pytest.mark.slow
def test_contact_force_points_from_a_into_b(result):
    """A puck shot at the wall (+x) pushes it along +x; the wall pushes back."""
    task = result.task
    m = task.scene.m
    theta = np.array([[2.0, 0.0]])
    shot = types.SimpleNamespace(task=task, theta=theta, replay=verify.simulate_c(task, theta))
    puck, wall = task.scene.geom("puck"), task.scene.geom("wall")
    frames = figures.plan_frames(shot, 0, [(puck, wall), (wall, puck)])
    on_wall, back = figures.plan_drawing(m, frames, trace=[]).forces
    assert on_wall.pair == (puck, wall) and 0 < len(on_wall.force) <= figures.FORCE_FRAMES
    # The wall is turned 10° about z: its normal is (cos 10°, sin 10°).
    normal = np.array([np.cos(np.radians(10)), np.sin(np.radians(10))])
    force = on_wall.force
    np.testing.assert_allclose(force / np.linalg.norm(force, axis=1, keepdims=True),
                               np.tile(normal, (len(force), 1)), atol=1e-6)
    assert np.all(np.abs(on_wall.point[:, 0] - 0.45) < 0.05)  # on the wall's near face
    np.testing.assert_array_equal(back.states, on_wall.states)
    np.testing.assert_allclose(back.force, -force)


def test_footprints_of_rotated_boxes_and_balls(tiny_task):
    """A box turned 10° about z has its corners where they should be; balls are discs."""
    m = figures_task(tiny_task).scene.m
    frames = geometry.replay_frames(m, m.qpos0, np.zeros((0, m.nq)))
    drawn = {(f.kind, m.geom(f.id).name if f.kind == "geom" else m.site(f.id).name): f
             for f in figures.plan_drawing(m, frames, trace=[]).start}
    assert set(drawn) == {("geom", "floor"), ("geom", "wall"), ("geom", "puck"), ("site", "goal")}
    wall = drawn["geom", "wall"].polygon
    c, s = np.cos(np.radians(10)), np.sin(np.radians(10))
    corner = np.array([0.5, 0.0]) + np.array([[c, -s], [s, c]]) @ [0.05, 1.0]
    assert len(wall) == 4 and np.min(np.linalg.norm(wall - corner, axis=1)) < 1e-9
    puck = drawn["geom", "puck"]
    np.testing.assert_allclose(np.linalg.norm(puck.polygon, axis=1), 0.04)
    assert puck.moving and not drawn["geom", "wall"].moving
    floor = drawn["geom", "floor"]
    assert floor.plane and np.allclose(np.abs(floor.polygon), 1.0)
    goal = drawn["site", "goal"]
    assert not goal.moving
    np.testing.assert_allclose(np.linalg.norm(goal.polygon - [-0.3, 0.3], axis=1), 0.1)
    np.testing.assert_allclose(goal.rgba, [0, 0.8, 0, geometry.SITE_OPACITY])


def test_import_leaves_matplotlib_global_state_alone():
    """No pyplot and no backend switch at import: figures render through Agg directly."""
    code = ("import sys, matplotlib; before = matplotlib.rcParams._get_backend_or_none(); "
            "import mjstamp.figures; "
            "assert 'matplotlib.pyplot' not in sys.modules; "
            "assert matplotlib.rcParams._get_backend_or_none() == before")
    subprocess.run([sys.executable, "-c", code], check=True)
