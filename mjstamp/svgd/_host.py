"""Arrays between the devices and the host: read over processes, written with their sharding.

The loop reads a step's diagnostics and state on the host (`fetch`) and writes
the guards' edits back (`set_rows`, `put`) with each array's own sharding, so
the compiled steps see the arrays they were built for.
"""

from __future__ import annotations

import jax
import numpy as np


def fetch(tree):
    """`jax.device_get` that also reads arrays spread over several processes' devices.

    N.B. such an array is gathered by a collective, which every process must
    reach at the same point; the loop's arrays are replicated by the caller's
    `jit` when its mesh spans processes (`mjstamp.parallel.replicate_outputs`),
    so it never needs one.
    """
    def one(x):
        if isinstance(x, jax.Array) and not x.is_fully_addressable and not x.is_fully_replicated:
            from jax.experimental import multihost_utils  # noqa: PLC0415

            return np.asarray(multihost_utils.process_allgather(x, tiled=True))
        return x

    return jax.device_get(jax.tree.map(one, tree))


def set_rows(array: jax.Array, idx: np.ndarray, rows) -> jax.Array:
    """`array` with rows `idx` set to `rows`, with the array's own sharding.

    N.B. written on the host and put back shard by shard: an array replicated
    over several processes' devices takes no eager `.at[].set` (it is not fully
    addressable), and the compiled step expects the sharding it was built for.
    """
    host = np.array(fetch(array))
    host[idx] = rows
    return put(host, array)


def put(host: np.ndarray, like: jax.Array) -> jax.Array:
    """A host array as a jax.Array with the sharding of `like` (over any processes)."""
    return jax.make_array_from_callback(host.shape, like.sharding, lambda i: host[i])
