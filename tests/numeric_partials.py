"""Central differences of sensor models' ``ground_to_image``, each model rebuilt for every
step: the slow, obvious reference the bulk projectors' analytic partials are tested
against (tests/test_projection.py, tests/test_pushbroom_projection.py)."""
import numpy as np


def central_partials(models, idx, ground, V, steps, h_g):
    """Partials of the image coordinates of ``ground`` (rows of image ``idx``) by each
    model's parameter vector ``V[k]`` (steps ``steps``: one per parameter, or one for all)
    and by the ground coordinates (step ``h_g``, metres): ``(n, 2, P)`` and ``(n, 2, 3)``."""
    n, P = idx.size, V.shape[1]
    steps = np.broadcast_to(np.asarray(steps, float), (P,))
    dp, dg = np.zeros((n, 2, P)), np.zeros((n, 2, 3))
    for k, m in enumerate(models):
        rows = idx == k
        g = ground[rows]
        for i in range(P):
            vp, vm = V[k].copy(), V[k].copy()
            vp[i] += steps[i]
            vm[i] -= steps[i]
            dp[rows, :, i] = (m.with_vector(vp).ground_to_image(g, clip=False)
                              - m.with_vector(vm).ground_to_image(g, clip=False)) / (
                2 * steps[i])
        mk = m.with_vector(V[k])
        for a in range(3):
            e = np.zeros(3)
            e[a] = h_g
            dg[rows, :, a] = (mk.ground_to_image(g + e, clip=False)
                              - mk.ground_to_image(g - e, clip=False)) / (2 * h_g)
    return dp, dg
