"""`mujoco.mjx`, imported without its stdout chatter.

N.B. mujoco.mjx prints "Failed to import warp: ..." to stdout when the optional
MuJoCo Warp backend is absent (it is, on CPU); that would corrupt `--json`
output, so the import runs with stdout captured.
"""

import contextlib
import io

with contextlib.redirect_stdout(io.StringIO()):
    from mujoco import mjx

__all__ = ["mjx"]
