"""Softplus with a sharpness beta, elementwise: the SDF networks' activation (``beta = 100``),
``softplus(x) = x`` where ``beta x > threshold`` (torch's rule, threshold 20), else
``log(1 + exp(beta x)) / beta``, written as ``(max(z, 0) + log1p(exp(-|z|))) / beta`` with
``z = beta x`` (no overflow for large z); ``log1p(e)`` as ``log(u) e / (u - 1)``, ``u = 1 + e``
(exact to rounding where ``u`` rounds to 1, where a plain ``log(1 + e)`` returns 0).

The backward: ``v_x = v_out`` where ``z > threshold``, else ``v_out sigmoid(z)``, with the
sigmoid from ``exp(-|z|)`` (no overflow). NaN inputs give NaN outputs and gradients.

Why a kernel: on an H200 torch's softplus took 5.4 of a 400x400 hash_sdf frame's 20.6 ms of GPU
time (0.96 G values, under a third of the copy bandwidth for one read and one write);
docs/design/training.md, issue 47's ninth round.
"""

from typing import Any

import warp as wp


@wp.func
def log1p_exp_neg(a: Any):
    """log(1 + exp(-a)) for a >= 0."""
    e = wp.exp(-a)
    u = a.dtype(1.0) + e
    if u == a.dtype(1.0):
        return e
    return wp.log(u) * e / (u - a.dtype(1.0))


@wp.kernel(enable_backward=False)
def softplus_fwd(
    x: wp.array(dtype=Any),  # [n]
    beta: Any,
    threshold: Any,
    out: wp.array(dtype=Any),  # [n]
):
    i = wp.tid()
    v = x[i]
    z = v * beta
    if z > threshold:
        out[i] = v
    else:
        out[i] = (wp.max(z, z.dtype(0.0)) + log1p_exp_neg(wp.abs(z))) / beta


@wp.kernel(enable_backward=False)
def softplus_bwd(
    x: wp.array(dtype=Any),  # [n]
    v_out: wp.array(dtype=Any),  # [n]
    beta: Any,
    threshold: Any,
    v_x: wp.array(dtype=Any),  # [n]
):
    i = wp.tid()
    z = x[i] * beta
    g = v_out[i]
    if z > threshold:
        v_x[i] = g
    else:
        e = wp.exp(-wp.abs(z))  # sigmoid(z): 1 / (1 + e) for z >= 0, e / (1 + e) below
        one = z.dtype(1.0)
        if z >= z.dtype(0.0):
            v_x[i] = g / (one + e)
        else:
            v_x[i] = g * e / (one + e)


def _overloads(dtype):
    a1 = wp.array(dtype=dtype)
    wp.overload(softplus_fwd, [a1, dtype, dtype, a1])
    wp.overload(softplus_bwd, [a1, a1, dtype, dtype, a1])


for _dt in (wp.float32, wp.float64):
    _overloads(_dt)
