"""Plan playback: MuJoCo scenes in meshcat, live or as a standalone HTML page.

    from mjstamp import viz
    viz.play("results/billiards", open_browser=True)       # live meshcat viewer
    viz.write_html("results/billiards", "billiards.html")  # offline page

What it is for: showing the plans of a results directory (what `mjstamp solve
--out` wrote) in 3-D, as `mjstamp view` does; it reads saved MuJoCo C states
and never plans. The one simulation it shows, a plan's perturbed replays
(`--perturbed`), comes from `verify.perturbed_replays`, the draws of the
plan's robustness score.

What it may import: mujoco, numpy, meshcat and its transport (zmq, umsgpack),
the standard library, and of mjstamp only `geometry` (poses, colours and
contact forces, shared with the PNG figures so the two cannot disagree),
`results` (the results files and their schema), `verify` (perturbed replays),
`fileio` and `errors`; not the solver, the tasks nor `figures`.

References:
  STAMP Fig. 6 (force arrows) and Fig. 7 (plan paths).
"""

from mjstamp.geometry import contact_force
from mjstamp.results import Results, load_results
from mjstamp.viz.playback import (
    Playback,
    Segment,
    ServerUnavailable,
    build_playback,
    html_page,
    play,
    start_server,
    write_html,
)
from mjstamp.viz.results import select_plans
from mjstamp.viz.scene import SceneObject, scene_commands, scene_objects

__all__ = [
    "Playback",
    "Results",
    "SceneObject",
    "Segment",
    "ServerUnavailable",
    "build_playback",
    "contact_force",
    "html_page",
    "load_results",
    "play",
    "scene_commands",
    "scene_objects",
    "select_plans",
    "start_server",
    "write_html",
]
