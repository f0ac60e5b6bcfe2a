"""Smoothed tracks: a recording's positions, headings and speeds low-pass filtered in time.

Video-tracked recordings carry measurement noise that no driver makes. NGSIM's speeds swing by
1-3 m/s over 1-2 s on cars that hold their speed (Punzo, Borzacchiello and Ciuffo 2011, "On
the assessment of vehicle trajectory data accuracy and application to the Next Generation
SIMulation (NGSIM) program data"); a world model trained on them learns that speed changes of
that size are how people drive, and samples them where the road gives no reason
(docs/world_model.md, "Why the first models lost to constant velocity on real logs").
``counterscene train --smooth-tracks`` smooths such a source's tracks before its windows are
cut; evaluation always reads the logs as recorded.

The filter is a local quadratic fit with Gaussian weights (a Savitzky-Golay filter whose
window weights fall off as a Gaussian of standard deviation ``sigma`` seconds, cut at 3 sigma),
run over each agent's every unbroken run of valid steps on its own. Each step's value is the
value at that step of the quadratic in time that fits its neighbours best, so a track at
constant velocity or constant acceleration comes out exactly as it went in, the ends of a run
included (there the fit is one-sided), and a turn keeps its curve (a car at 5-15 m/s on a
10-50 m circle moves by under 4 mm, 2 cm at a run's ends, with ``sigma`` 0.5 s): the filter
takes out the noise and leaves the manoeuvres. A plain moving average would not: it shifts
a car that speeds up by ``a sigma^2 / 2`` and pulls a turning car's path inward. A run
shorter than 3 steps is left as it is. Headings are unwrapped before filtering and wrapped
back.
"""

from __future__ import annotations

import numpy as np

from counterscene_env.geometry import wrap_angle
from counterscene_env.scene.core import Scene

#: The weights reach this many standard deviations either side.
KERNEL_REACH = 3.0


def local_quadratic_weights(n: int, sigma_steps: float) -> tuple[np.ndarray, np.ndarray]:
    """The filter of a run of ``n`` >= 3 steps (module docstring) as ``(W, J)``, both ``[n,
    2 r + 1]``: step i's filtered value is ``sum_k W[i, k] values[J[i, k]]``, the value at
    step i of the quadratic fitted, with Gaussian weights, to its neighbours within ``r =
    KERNEL_REACH * sigma_steps`` steps (``sigma_steps`` > 0). Banded, so a long log costs
    ``n r``, not ``n^2``."""
    if not sigma_steps > 0:
        raise ValueError(f"sigma_steps must be > 0, got {sigma_steps}")
    # At least two neighbours either side, so that a one-sided fit at a run's end is determined.
    r = int(max(np.ceil(KERNEL_REACH * sigma_steps), 2))
    offset = np.arange(-r, r + 1)[None, :].repeat(n, 0)  # [n, 2r+1] j - i, steps
    J = np.arange(n)[:, None] + offset
    inside = (J >= 0) & (J < n)
    w = np.exp(-0.5 * (offset / sigma_steps) ** 2) * inside
    X = np.stack([np.ones_like(offset), offset, offset**2], -1).astype(float)  # [n, 2r+1, 3]
    A = np.einsum("ik,ikp,ikq->ipq", w, X, X)  # [n, 3, 3] weighted normal equations
    # The fitted value at the step itself (offset 0) is the fit's constant term.
    e0 = np.linalg.solve(A, np.broadcast_to(np.eye(3)[0], (n, 3))[..., None])[..., 0]
    return np.einsum("ip,ikp,ik->ik", e0, X, w), J.clip(0, n - 1)


def smooth_run(values: np.ndarray, sigma_steps: float) -> np.ndarray:
    """One unbroken run ``[T, C]`` filtered along T (module docstring); runs shorter than 3
    steps come back unchanged."""
    if values.shape[0] < 3:
        return values.copy()
    W, J = local_quadratic_weights(values.shape[0], sigma_steps)
    return np.einsum("ik,ikc->ic", W, values[J])


def valid_runs(valid: np.ndarray) -> list[tuple[int, int]]:
    """``[start, stop)`` of each unbroken run of True in ``valid [T]``."""
    edges = np.diff(np.concatenate([[0], valid.astype(np.int8), [0]]))
    return list(zip(np.flatnonzero(edges == 1), np.flatnonzero(edges == -1), strict=True))


def smooth_tracks(scene: Scene, sigma: float) -> Scene:
    """``scene`` with every agent's positions [m], headings [rad] and speeds [m/s] filtered
    with Gaussian weights of standard deviation ``sigma`` seconds (module docstring);
    validity, extents and the road are unchanged, and the metadata gains
    ``"smoothed_sigma_s"``.

    Raises:
        ValueError: ``sigma`` not > 0.
    """
    if not sigma > 0:
        raise ValueError(f"sigma must be > 0 seconds, got {sigma}")
    positions, yaws, speeds = scene.positions.copy(), scene.yaws.copy(), scene.speeds.copy()
    for i in range(scene.num_agents):
        for a, b in valid_runs(scene.valid[i]):
            track = np.column_stack(
                [positions[i, a:b], np.unwrap(yaws[i, a:b]), speeds[i, a:b]]
            )  # [n, 4]
            smooth = smooth_run(track, sigma / scene.dt)
            positions[i, a:b] = smooth[:, :2]
            yaws[i, a:b] = wrap_angle(smooth[:, 2])
            # The one-sided fit at a run's end can dip a start from standstill below 0: a
            # run that never reverses keeps speeds >= 0.
            speeds[i, a:b] = smooth[:, 3] if (track[:, 3] < 0).any() else smooth[:, 3].clip(0)
    metadata = {**scene.metadata, "smoothed_sigma_s": float(sigma)}
    return scene.replace(positions=positions, yaws=yaws, speeds=speeds, metadata=metadata)
