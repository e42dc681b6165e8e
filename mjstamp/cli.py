"""The `mjstamp` command line.

Bad input (an unknown scene, a malformed MJCF, a bad option) prints one line,
`mjstamp: error: ...`, and exits with status 2; no traceback.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
from pathlib import Path

from mjstamp.errors import MjstampError

DEFAULT_CACHE = Path.home() / ".cache" / "mjstamp" / "jax"


def configure_jax(*, precision: str = "float64") -> None:
    """Process-wide JAX settings of the CLI: precision and compilation cache.

    N.B. float64 is the default precision: float32 reverse-mode gradients
    through MJX's constraint solver go NaN on contact (see
    `mjstamp.scenes.gradsafe`). The persistent compilation cache turns a 20-45 s
    compile of an MJX rollout into a few seconds in the next process.
    """
    import jax

    jax.config.update("jax_enable_x64", precision == "float64")
    cache = os.environ.get("JAX_COMPILATION_CACHE_DIR") or str(DEFAULT_CACHE)
    jax.config.update("jax_compilation_cache_dir", cache)
    jax.config.update("jax_persistent_cache_min_compile_time_secs", 0.5)


def _load_scene(name: str, **kwargs):
    from mjstamp.scenes import Scene

    looks_like_path = name.endswith(".xml") or os.sep in name
    if looks_like_path:
        return Scene(name, **kwargs)
    return Scene.shipped(name, **kwargs)


def _cmd_check(args) -> int:
    from mjstamp.scenes.check import check_scene

    scene = _load_scene(args.scene)
    say = (lambda msg: print(f"[check] {msg}", file=sys.stderr)) if not args.quiet else None
    report = check_scene(scene, particles=args.particles, seed=args.seed, progress=say)
    if args.json:
        print(json.dumps(report))
        return 0
    print(f"scene            {report['scene']} ({report['precision']}, "
          f"{report['solver']}, ls_iterations={report['ls_iterations']})")
    print(f"particles        {report['particles']} x {report['horizon']} steps, "
          f"{report['dim']} coordinates each")
    print(f"non-finite grads {report['nonfinite']} ({report['nonfinite_fraction']:.1%})")
    if report["rel_err_median"] is not None:
        print(f"AD vs FD rel err median {report['rel_err_median']:.2e}, "
              f"p95 {report['rel_err_p95']:.2e}")
    print(f"value-and-grad   {report['us_per_particle_step']:.1f} us per particle-step "
          f"(compile {report['compile_s']:.1f} s)")
    return 0


def build_parser() -> argparse.ArgumentParser:
    """The argument parser (exposed for tests and docs)."""
    parser = argparse.ArgumentParser(
        prog="mjstamp",
        description="Differentiable task and motion planning (STAMP) on MuJoCo MJX.",
    )
    sub = parser.add_subparsers(dest="command", required=True)
    check = sub.add_parser(
        "check",
        help="gradient health of a scene: NaN rate, AD vs finite differences, speed",
    )
    check.add_argument("scene", help="shipped scene name (e.g. billiards) or MJCF path")
    check.add_argument("--particles", type=int, default=256, help="random particles")
    check.add_argument("--seed", type=int, default=0)
    check.add_argument(
        "--precision",
        choices=("float64", "float32"),
        default="float64",
        help="MJX precision (float32 gradients through contacts can go NaN)",
    )
    check.add_argument("--json", action="store_true", help="print one JSON object")
    check.add_argument("--quiet", action="store_true", help="no progress on stderr")
    check.set_defaults(func=_cmd_check)
    return parser




def main(argv: list[str] | None = None) -> int:
    """Entry point of the `mjstamp` console script."""
    parser = build_parser()
    args = parser.parse_args(argv)
    try:
        configure_jax(precision=getattr(args, "precision", "float64"))
        return args.func(args)
    except MjstampError as e:
        print(f"mjstamp: error: {e}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print("mjstamp: interrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":
    sys.exit(main())
