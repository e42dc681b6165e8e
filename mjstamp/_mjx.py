"""MuJoCo plumbing every layer may use: a quiet `mujoco.mjx`, source rewrites, model bytes.

It holds `mujoco.mjx` imported without its stdout chatter, `rewrite` (an MJX
function's source with textual edits) and `model_bytes` (for fingerprints).

N.B. mujoco.mjx prints "Failed to import warp: ..." to stdout when the optional
MuJoCo Warp backend is absent (it is, on CPU); that would corrupt `--json`
output, so the import runs with stdout captured.
"""

import contextlib
import inspect
import io
import textwrap
from collections.abc import Callable

import mujoco
import numpy as np

with contextlib.redirect_stdout(io.StringIO()):
    from mujoco import mjx

__all__ = ["model_bytes", "mjx", "rewrite"]


def rewrite(module, qualname: str, edits: list[tuple[str, str]], *,
            extra: dict[str, object] | None = None) -> Callable:
    """Returns a copy of ``module.<qualname>`` with textual edits applied.

    Args:
      module: the module that defines the function.
      qualname: its name there ("solve", "_LSPoint.create").
      edits: (old, new) source texts; each old must occur exactly once.
      extra: names the new source uses, added to the module's globals.

    Raises:
      RuntimeError: an old text is not found exactly once (MJX changed).
    """
    owner, _, name = qualname.rpartition(".")
    holder = getattr(module, owner) if owner else module
    fn = inspect.unwrap(getattr(holder, name))
    fn = getattr(fn, "__func__", fn)  # classmethod -> function
    src = textwrap.dedent(inspect.getsource(fn))
    for old, new in edits:
        n = src.count(old)
        if n != 1:
            raise RuntimeError(
                f"mjstamp: expected exactly one `{old}` in {module.__name__}."
                f"{qualname}, found {n}; MJX changed, re-audit the patch."
            )
        src = src.replace(old, new)
    if src.startswith("@classmethod"):
        src = src[len("@classmethod") :].lstrip()
    # N.B. exec in the solver module's own globals so that every other name the
    # function uses (jp, math, support, ConeType, ...) resolves exactly as in
    # the original; only the names of `extra` are added.
    glb = module.__dict__
    for k, v in (extra or {}).items():
        glb.setdefault(k, v)
    loc: dict[str, object] = {}
    exec(compile(src, f"<gradsafe:{qualname}>", "exec"), glb, loc)  # pylint: disable=exec-used
    return loc[name]


def model_bytes(m: mujoco.MjModel) -> bytes:
    """The compiled model as bytes (mj_saveModel), for fingerprints."""
    buffer = np.empty(mujoco.mj_sizeModel(m), np.uint8)
    mujoco.mj_saveModel(m, None, buffer)
    return buffer.tobytes()
