"""The MJX solver patch: finite gradients where MJX's own go NaN, same forward values."""

import json
import subprocess
import sys

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from mjstamp.scenes import gradsafe


def test_safe_ops_match_plain_ops_and_stay_finite_at_zero():
    x = jnp.array([0.0, 1e-30, 0.5, 2.0])
    np.testing.assert_array_equal(gradsafe.safe_sqrt(x), jnp.sqrt(x))
    g = jax.grad(lambda v: jnp.sum(gradsafe.safe_sqrt(v)))(x)
    assert np.isfinite(g).all() and g[0] == 0.0
    np.testing.assert_allclose(g[2:], 0.5 / np.sqrt(x[2:]))
    y = jnp.array([1e-30, 2.0])
    np.testing.assert_array_equal(gradsafe.safe_div(x[:2], y), x[:2] / y)
    gx, gy = jax.grad(lambda a, b: jnp.sum(gradsafe.safe_div(a, b)), argnums=(0, 1))(
        jnp.array([0.0, 3.0]), y
    )
    assert np.isfinite(gx).all() and np.isfinite(gy).all()
    np.testing.assert_allclose([gx[1], gy[1]], [0.5, -3.0 / 4.0])


# Two balls with hinges and elliptic-cone contacts, float32: MJX's own reverse-mode
# gradients are NaN here; the same rollout after patch_mjx() must be finite, with
# bit-identical forward values.
_SCRIPT = r"""
import json, jax, jax.numpy as jnp, numpy as np, mujoco
from mujoco import mjx
XML = '''<mujoco><option timestep="0.01" gravity="0 0 0" cone="elliptic" iterations="1"
  ls_iterations="4"/>
  <worldbody><geom type="box" pos="0.6 0 0" size="0.05 1 0.05"/>
  <body name="a"><joint type="slide" axis="1 0 0"/><joint type="slide" axis="0 1 0"/>
    <joint type="hinge" axis="0 0 1"/><geom type="sphere" size="0.04" mass="0.2" condim="3"/></body>
  <body name="b" pos="0.3 0 0"><joint type="slide" axis="1 0 0"/><joint type="slide" axis="0 1 0"/>
    <joint type="hinge" axis="0 0 1"/><geom type="sphere" size="0.04" mass="0.2" condim="3"/></body>
  </worldbody></mujoco>'''
m = mujoco.MjModel.from_xml_string(XML)
def run():
    mx = mjx.put_model(m); d0 = mjx.make_data(mx)
    def loss(v):
        def step(d, _):
            d = mjx.step(mx, d)
            return d, d.qpos
        d = d0.replace(qvel=jnp.zeros(mx.nv).at[:2].set(v))
        return jnp.sum(jax.lax.scan(step, d, None, length=40)[1][-1, 3:5])
    v = jnp.asarray(np.random.default_rng(0).uniform(-2, 2, (16, 2)), jnp.float32)
    val, g = jax.jit(jax.vmap(jax.value_and_grad(loss)))(v)
    return np.asarray(val), np.asarray(g)
val0, g0 = run()
from mjstamp.scenes import gradsafe
gradsafe.patch_mjx()
val1, g1 = run()
print(json.dumps({"nan_before": int((~np.isfinite(g0)).any(1).sum()),
                  "nan_after": int((~np.isfinite(g1)).any(1).sum()),
                  "same_forward": bool(np.array_equal(val0, val1))}))
"""


@pytest.mark.slow
def test_patch_removes_nan_gradients_of_elliptic_contacts_in_float32():
    out = subprocess.run([sys.executable, "-c", _SCRIPT], capture_output=True, text=True,
                         check=True, env={"JAX_ENABLE_X64": "0", "PATH": ""})
    result = json.loads(out.stdout.strip().splitlines()[-1])
    assert result["nan_before"] > 0  # the failure the patch exists for
    assert result["nan_after"] == 0
    assert result["same_forward"]


def test_patch_is_idempotent_and_applied_by_scene(billiards):
    assert gradsafe.is_patched()
    gradsafe.patch_mjx()
    assert gradsafe.is_patched()
