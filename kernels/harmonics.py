"""Real spherical harmonics of unit directions (degree 1..4, the orthonormal basis with
instant-ngp's / tiny-cuda-nn's constants), written after a feature row: the colour MLP's input
``[features | SH(d)]`` in one pass, instead of a dozen elementwise ops, a stack and a
concatenation. No gradient for the directions (the caller checks they need none); the features'
gradient is the first columns of the output's (the bridge returns that slice).

Each value is the pure-torch formula's (``warpnerf.ops.encoding.spherical_harmonics``), term for
term in the same order, e.g. ``c * y * (3 x^2 - y^2)`` = ``((c y) (3 x^2 - y^2))``.
"""

import warp as wp


@wp.kernel(enable_backward=False)
def sh_concat(
    features: wp.array2d(dtype=float),  # [n, F]
    directions: wp.array(dtype=wp.vec3),  # [n]
    degree: int,  # 1..4: degree^2 values
    out: wp.array2d(dtype=float),  # [n, F + degree^2] out
):
    i = wp.tid()
    nf = features.shape[1]
    for k in range(nf):
        out[i, k] = features[i, k]
    d = directions[i]
    x = d[0]
    y = d[1]
    z = d[2]
    x2 = x * x
    y2 = y * y
    z2 = z * z
    out[i, nf] = 0.28209479177387814
    if degree > 1:
        out[i, nf + 1] = -0.48860251190291987 * y
        out[i, nf + 2] = 0.48860251190291987 * z
        out[i, nf + 3] = -0.48860251190291987 * x
    if degree > 2:
        out[i, nf + 4] = 1.0925484305920792 * x * y
        out[i, nf + 5] = -1.0925484305920792 * y * z
        out[i, nf + 6] = 0.94617469575755997 * z2 - 0.31539156525251999
        out[i, nf + 7] = -1.0925484305920792 * x * z
        out[i, nf + 8] = 0.54627421529603959 * (x2 - y2)
    if degree > 3:
        out[i, nf + 9] = 0.59004358992664352 * y * (3.0 * x2 - y2)
        out[i, nf + 10] = 2.8906114426405538 * x * y * z
        out[i, nf + 11] = 0.45704579946446572 * y * (1.0 - 5.0 * z2)
        out[i, nf + 12] = 0.3731763325901154 * z * (5.0 * z2 - 3.0)
        out[i, nf + 13] = 0.45704579946446572 * x * (1.0 - 5.0 * z2)
        out[i, nf + 14] = 1.4453057213202769 * z * (x2 - y2)
        out[i, nf + 15] = 0.59004358992664352 * x * (x2 - 3.0 * y2)
