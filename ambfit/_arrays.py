"""NumPy for concrete values, JAX for traced ones.

An eager JAX operation on concrete arrays (``jnp.asarray`` of a NumPy array among them) compiles a small program
for each new shape and dtype it meets; a fit meets many shapes (its problems, the designs a diagnosis simulates,
its models' parameters), and a compiled solve converts NumPy inputs at its call anyway.  Code that builds arrays
for it therefore works in NumPy unless a value is traced (inside ``jit``, ``vmap`` or a derivative).
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

Array = np.ndarray | jax.Array
"""A NumPy array (built from concrete values) or a JAX one (traced, or a compiled program's output)."""


def frozen(a, dtype=None) -> np.ndarray:
    """A read-only NumPy copy of ``a`` (of ``dtype``): values, not buffers to write into."""
    a = np.array(a, dtype=dtype)
    a.flags.writeable = False
    return a


def traced(*values) -> bool:
    """Whether any leaf of ``values`` is a JAX tracer."""
    return any(isinstance(v, jax.core.Tracer) for v in jax.tree_util.tree_leaves(values))


def numpy_unless_traced(*values):
    """``jax.numpy`` when any leaf of ``values`` is traced, else NumPy."""
    return jnp if traced(*values) else np
