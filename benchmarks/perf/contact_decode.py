"""The decode's contacts: MuJoCo C's colliders per state against the JAX signed distances.

A plan's contact symbols are read off its replay: whether each symbol's geom
pair touches at each state. `verify.Replay` asks MuJoCo C
(`mjstamp.kinematics.touching`: `mj_kinematics` once per state, then
`mj_geomDistance` at zero margin per pair); the JAX signed distance of a pair
on MJX kinematics, measured beside it, costs 0.1 ms or more per state for a
curved pair and does not exist for some (cylinder-box, cylinder-mesh).

Per geom pair, on a two-body model (both geoms on free joints), states whose
second geom sits at a random direction and offset within 1.5 times the sum of
both bounding radii from the first, both turned at random (`touch_share` of
them touch): the µs per state of

- `c_us`: `touching` asking C at every state, one symbol (kinematics
  included: a state's kinematics is shared by all its symbols), the worst case
  (a `Replay` asks only where a cheap bound leaves contact possible);
- `kinematics_us`: the `mj_kinematics` loop alone (so the pair's own part is
  `c_us - kinematics_us`);
- `jax_us`: the JAX signed distance (jitted, vmapped over the states, float64,
  compile excluded; poses given, kinematics not included), or null where the
  pair has none;

and `agree`: the share of states where C's touch equals JAX's sd < 0. Median
of `--repeats`. Prints one JSON object.

Usage: python benchmarks/perf/contact_decode.py [--pairs sphere-box,box-box]
       [--states 20000] [--repeats 3] [--no-jax] [--save FILE]
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

if __package__ in (None, ""):  # run by its path: the repository root holds `benchmarks`
    sys.path.insert(0, str(Path(__file__).resolve().parents[2]))
from benchmarks.common import save_json  # noqa: E402

PAIRS = ("sphere-box", "box-box", "cylinder-box", "cylinder-cylinder", "mesh-box")

_GEOMS = {
    "sphere": 'type="sphere" size="0.05"',
    "box": 'type="box" size="0.05 0.08 0.03"',
    "cylinder": 'type="cylinder" size="0.04 0.06"',
    "capsule": 'type="capsule" size="0.03 0.05"',
    "ellipsoid": 'type="ellipsoid" size="0.05 0.04 0.03"',
    "mesh": 'type="mesh" mesh="wedge"',
}

_MESH = """<asset><mesh name="wedge" vertex="-.06 -.04 -.03  .06 -.04 -.03  -.06 .04 -.03
  .06 .04 -.03  -.06 -.01 .03  .06 -.01 .03  -.06 .01 .03  .06 .01 .03"/></asset>"""


def pair_model(name: str):
    """A model of two geoms of the pair's types, each on a free body."""
    import mujoco

    kinds = name.split("-")
    if len(kinds) != 2 or any(k not in _GEOMS for k in kinds):
        raise SystemExit(f"--pairs: {name!r}; valid: TYPE-TYPE with TYPE one of "
                         f"{', '.join(_GEOMS)}")
    bodies = "".join(f'<body name="b{i}"><freejoint/><geom name="g{i}" {_GEOMS[k]}/></body>'
                     for i, k in enumerate(kinds))
    xml = f'<mujoco><option gravity="0 0 0"/>{_MESH}<worldbody>{bodies}</worldbody></mujoco>'
    return mujoco.MjModel.from_xml_string(xml)


def states(m, n: int, seed: int):
    """(n, 14) qpos: geom 1 at the origin, geom 2 within 1.5 x both bounding radii, turned."""
    import numpy as np

    rng = np.random.default_rng(seed)
    q = rng.normal(size=(n, 2, 4))
    q /= np.linalg.norm(q, axis=-1, keepdims=True)
    direction = rng.normal(size=(n, 3))
    direction /= np.linalg.norm(direction, axis=1, keepdims=True)
    reach = rng.uniform(0.0, 1.5 * m.geom_rbound.sum(), size=(n, 1))
    qpos = np.zeros((n, 14))
    qpos[:, 3:7], qpos[:, 7:10], qpos[:, 10:14] = q[:, 0], reach * direction, q[:, 1]
    return qpos


def _median_time(fn, repeats: int) -> float:
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t0)
    return sorted(times)[len(times) // 2]


def measure(name: str, n: int, repeats: int, jax_too: bool, seed: int = 0) -> dict:
    """One pair's row (see the module docstring)."""
    import mujoco

    from mjstamp import kinematics

    m = pair_model(name)
    qpos = states(m, n, seed)
    pairs = [(0, 1)]
    touch = kinematics.touching(m, qpos, pairs)[:, 0]
    c = _median_time(lambda: kinematics.touching(m, qpos, pairs), repeats)
    d = mujoco.MjData(m)

    def kinematics_only():
        for q in qpos:
            d.qpos[:] = q
            mujoco.mj_kinematics(m, d)

    kin = _median_time(kinematics_only, repeats)
    row = {"pair": name, "states": n, "touch_share": float(touch.mean()),
           "c_us": c / n * 1e6, "kinematics_us": kin / n * 1e6, "jax_us": None, "agree": None}
    if jax_too:
        row.update(_jax(m, qpos, touch, repeats))
    return row


def _jax(m, qpos, touch, repeats: int) -> dict:
    """The JAX signed distance's µs per state and its agreement with C's touch."""
    import jax
    import jax.numpy as jnp
    import numpy as np

    from mjstamp.distance import make_distance_fn
    from mjstamp.errors import MjstampError
    from mjstamp.kinematics import poses

    try:
        fn = make_distance_fn(m, 0, 1)
    except MjstampError:
        return {}
    p = poses(m, qpos, ("geom_xpos", "geom_xmat"))
    xpos, xmat = jnp.asarray(p["geom_xpos"]), jnp.asarray(p["geom_xmat"])
    batched = jax.jit(jax.vmap(fn))
    sd = np.asarray(batched(xpos, xmat))
    t = _median_time(lambda: jax.block_until_ready(batched(xpos, xmat)), repeats)
    return {"jax_us": t / len(qpos) * 1e6, "agree": float(((sd < 0) == touch).mean())}


def main(argv=None) -> None:
    """Measures the pairs and prints (and with --save writes) the JSON."""
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--pairs", default=",".join(PAIRS),
                        help=f"comma-separated TYPE-TYPE (default: {','.join(PAIRS)})")
    parser.add_argument("--states", type=int, default=20000)
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--no-jax", action="store_true", help="skip the JAX signed distances")
    parser.add_argument("--save", default=None, help="also write the JSON here")
    args = parser.parse_args(argv)
    if args.states < 1 or args.repeats < 1:
        raise SystemExit(f"--states={args.states} and --repeats={args.repeats} must be >= 1")
    import jax

    jax.config.update("jax_enable_x64", True)
    rows = [measure(p, args.states, args.repeats, not args.no_jax)
            for p in args.pairs.split(",")]
    out = {"benchmark": "contact_decode", "unit": "us per state, one symbol", "rows": rows}
    print(json.dumps(out, indent=2))
    if args.save:
        save_json(args.save, out, indent=2, newline=True)


if __name__ == "__main__":
    main()
