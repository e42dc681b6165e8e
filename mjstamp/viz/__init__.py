"""Plan playback: MuJoCo scenes in meshcat, live or as a standalone HTML page.

    from mjstamp import viz
    viz.play("results/billiards", open_browser=True)       # live meshcat viewer
    viz.write_html("results/billiards", "billiards.html")  # offline page

References:
  STAMP Fig. 6 (force arrows) and Fig. 7 (plan paths).
"""

from mjstamp.viz.forces import contact_force
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
from mjstamp.viz.results import Results, load_results, select_plans
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
