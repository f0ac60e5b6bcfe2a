"""Oriented-box geometry for collision, clearance, off-road and time-to-collision checks.

This module's one job is the vectorised geometry the metrics and the simulator share: corners,
overlap (separating axis theorem), drivable-area membership and box distance, plus angle
wrapping and frame transforms. Constant-velocity time to collision, built on the same
separating axes, is ``counterscene_env/ttc.py``. It is a lower layer: plain numpy
and shapely, no scene types.

Conventions (docs/design.md, "Ego-centred frame"): SI units, world frame, yaw in rad from +x counter-clockwise, a box is
its centre ``[2] m``, yaw ``[] rad`` and extents ``(length, width) [2] m`` with the length along
the heading.

Validity: every function that takes a ``valid`` mask treats an agent as present only where it is
valid *and* its centre, yaw and extents are finite. An invalid agent only drops its own row and
column: it never disables the checks between other agents (the public reference code skips all
checks of a step as soon as one agent is NaN).
"""

from __future__ import annotations

import numpy as np
import shapely

#: Boxes overlap only if they interpenetrate by more than this along every separating axis, m.
#: So boxes that merely touch (zero-area contact, up to float rounding) do not overlap.
OVERLAP_TOL = 1e-6

# Upper bound on the number of box pairs evaluated at once by the chunked helpers, so that
# [T, N, N] problems stay within a few tens of MB whatever T and N are.
_MAX_PAIRS_PER_CHUNK = 1 << 20


# ---------------------------------------------------------------------- boxes
def box_corners(centers: np.ndarray, yaws: np.ndarray, extents: np.ndarray) -> np.ndarray:
    """Corners of oriented boxes, counter-clockwise from the front-right corner.

    Args:
        centers: ``[..., 2]`` m, box centres.
        yaws: ``[...]`` rad, headings.
        extents: ``[..., 2]`` m, (length, width); broadcast against ``centers``.

    Returns:
        ``[..., 4, 2]`` m: front-right, front-left, rear-left, rear-right (counter-clockwise,
        so the shoelace area is positive).
    """
    centers = np.asarray(centers, dtype=np.float64)
    yaws = np.asarray(yaws, dtype=np.float64)
    extents = np.asarray(extents, dtype=np.float64)
    half = 0.5 * extents
    # Local-frame corners (x along the heading, y to the left), scaled by the half extents.
    signs = np.array([[1.0, -1.0], [1.0, 1.0], [-1.0, 1.0], [-1.0, -1.0]])
    local = signs * half[..., None, :]  # [..., 4, 2]
    c, s = np.cos(yaws)[..., None], np.sin(yaws)[..., None]
    x = local[..., 0] * c - local[..., 1] * s
    y = local[..., 0] * s + local[..., 1] * c
    return centers[..., None, :] + np.stack([x, y], axis=-1)


def sat_terms(
    yaws_a: np.ndarray, extents_a: np.ndarray, yaws_b: np.ndarray, extents_b: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Separating axes and the summed half-projections of box pairs.

    For two rectangles the SAT needs four axes: the heading u and left normal n of each box.
    Box k projects onto a unit axis e with half-length ``l_k/2 |u_k.e| + w_k/2 |n_k.e|``; with
    ``D = yaw_b - yaw_a`` the dot products between the two frames are ``u_b.u_a = n_b.n_a = cos D``
    and ``|n_b.u_a| = |u_b.n_a| = |sin D|``, so the sums of half-projections are closed form.

    Returns:
        ``cos, sin`` of the four axes (u_a, n_a, u_b, n_b), each ``[..., 4]``, and radii
        ``[..., 4]`` m, the sum of both boxes' half-projections on each axis. The boxes overlap
        iff the centre offset projects shorter than the radius on all four axes.
    """
    hl_a, hw_a = 0.5 * extents_a[..., 0], 0.5 * extents_a[..., 1]
    hl_b, hw_b = 0.5 * extents_b[..., 0], 0.5 * extents_b[..., 1]
    diff = yaws_b - yaws_a
    c, s = np.abs(np.cos(diff)), np.abs(np.sin(diff))
    radii = np.stack(
        [
            hl_a + hl_b * c + hw_b * s,  # on u_a
            hw_a + hl_b * s + hw_b * c,  # on n_a
            hl_b + hl_a * c + hw_a * s,  # on u_b
            hw_b + hl_a * s + hw_a * c,  # on n_b
        ],
        axis=-1,
    )
    ca, sa, cb, sb = np.broadcast_arrays(
        np.cos(yaws_a), np.sin(yaws_a), np.cos(yaws_b), np.sin(yaws_b)
    )
    # n = (-sin, cos) is u rotated by +90 deg.
    axis_cos = np.stack([ca, -sa, cb, -sb], axis=-1)
    axis_sin = np.stack([sa, ca, sb, cb], axis=-1)
    return axis_cos, axis_sin, radii


def project_on_axes(vec: np.ndarray, axis_cos: np.ndarray, axis_sin: np.ndarray) -> np.ndarray:
    """``[..., 4]`` projections of ``[..., 2]`` vectors on the four SAT axes."""
    return vec[..., 0, None] * axis_cos + vec[..., 1, None] * axis_sin


def present(centers: np.ndarray, yaws: np.ndarray, extents: np.ndarray, valid) -> np.ndarray:
    """``[...]`` bool: valid and with finite centre, yaw and extents."""
    ok = np.isfinite(centers).all(-1) & np.isfinite(yaws) & np.isfinite(extents).all(-1)
    return ok if valid is None else ok & np.asarray(valid, dtype=bool)


def sanitise_boxes(
    centers: np.ndarray, yaws: np.ndarray, extents: np.ndarray, ok: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Zero out absent boxes so that their NaNs raise no warnings and reach no other pair."""
    centers = np.where(ok[..., None], centers, 0.0)
    yaws = np.where(ok, yaws, 0.0)
    extents = np.where(ok[..., None], extents, 1.0)
    return centers, yaws, extents


def boxes_overlap(
    centers_a: np.ndarray,
    yaws_a: np.ndarray,
    extents_a: np.ndarray,
    centers_b: np.ndarray,
    yaws_b: np.ndarray,
    extents_b: np.ndarray,
) -> np.ndarray:
    """Element-wise oriented-box overlap of box a and box b (numpy broadcasting).

    Args:
        centers_a, centers_b: ``[..., 2]`` m.
        yaws_a, yaws_b: ``[...]`` rad.
        extents_a, extents_b: ``[..., 2]`` m, (length, width).

    Returns:
        ``[...]`` bool, True where the boxes interpenetrate by more than :data:`OVERLAP_TOL`
        along every separating axis. Touching boxes do not overlap; any non-finite input gives
        False for that element only.
    """
    ca, ya, ea = (np.asarray(x, dtype=np.float64) for x in (centers_a, yaws_a, extents_a))
    cb, yb, eb = (np.asarray(x, dtype=np.float64) for x in (centers_b, yaws_b, extents_b))
    ok_a, ok_b = present(ca, ya, ea, None), present(cb, yb, eb, None)
    ca, ya, ea = sanitise_boxes(ca, ya, ea, ok_a)
    cb, yb, eb = sanitise_boxes(cb, yb, eb, ok_b)
    axis_cos, axis_sin, radii = sat_terms(ya, ea, yb, eb)
    offset = np.abs(project_on_axes(cb - ca, axis_cos, axis_sin))
    # Strict inequality with a tolerance: separated (or touching) on any one axis => no overlap.
    return (offset < radii - OVERLAP_TOL).all(-1) & ok_a & ok_b


def _pair_overlap_batched(
    centers: np.ndarray, yaws: np.ndarray, extents: np.ndarray, ok: np.ndarray
) -> np.ndarray:
    """``[B, N, N]`` bool from ``[B, N, 2]`` centres, ``[B, N]`` yaws, ``[N, 2]`` extents.

    Overlap is symmetric, so only pairs i < j are tested and mirrored. Pairs whose centres are
    farther apart than the sum of the boxes' half-diagonals cannot overlap and skip the SAT: in
    a traffic scene that is nearly all of them.
    """
    b, n = yaws.shape
    out = np.zeros((b, n, n), dtype=bool)
    if n < 2:
        return out
    ii, jj = np.triu_indices(n, k=1)
    reach = 0.5 * np.hypot(extents[:, 0], extents[:, 1])  # [N] m, bounding-circle radii
    reach = np.where(np.isfinite(reach), reach, 0.0)
    chunk = max(1, _MAX_PAIRS_PER_CHUNK // len(ii))
    for s in range(0, b, chunk):  # chunks of time steps, not pairs: bounded memory
        c, y, k = centers[s : s + chunk], yaws[s : s + chunk], ok[s : s + chunk]
        c = np.where(k[..., None], c, 0.0)  # absent agents: no NaN in the distance test
        d2 = ((c[:, jj] - c[:, ii]) ** 2).sum(-1)  # [B, P] m^2
        cand = k[:, ii] & k[:, jj] & (d2 < (reach[ii] + reach[jj]) ** 2)
        bt, pt = np.nonzero(cand)
        i, j = ii[pt], jj[pt]
        hit = boxes_overlap(c[bt, i], y[bt, i], extents[i], c[bt, j], y[bt, j], extents[j])
        out[s + bt[hit], i[hit], j[hit]] = True
    out |= out.transpose(0, 2, 1)
    return out


def pairwise_overlap(
    centers: np.ndarray, yaws: np.ndarray, extents: np.ndarray, valid: np.ndarray
) -> np.ndarray:
    """Which pairs of N oriented boxes overlap (separating axis theorem, all pairs at once).

    Args:
        centers: ``[N, 2]`` m.
        yaws: ``[N]`` rad.
        extents: ``[N, 2]`` m, (length, width).
        valid: ``[N]`` bool. Invalid agents (whose entries may be NaN) get False in their row
            and column and do not affect any other pair.

    Returns:
        ``[N, N]`` bool, symmetric, False on the diagonal. Touching boxes do not overlap
        (see :data:`OVERLAP_TOL`).
    """
    centers = np.asarray(centers, dtype=np.float64)
    yaws = np.asarray(yaws, dtype=np.float64)
    extents = np.asarray(extents, dtype=np.float64)
    ok = present(centers, yaws, extents, valid)
    return _pair_overlap_batched(centers[None], yaws[None], extents, ok[None])[0]


def overlaps_over_time(
    positions: np.ndarray, yaws: np.ndarray, extents: np.ndarray, valid: np.ndarray
) -> np.ndarray:
    """:func:`pairwise_overlap` at every step of a log, vectorised over time.

    Args:
        positions: ``[N, T, 2]`` m.
        yaws: ``[N, T]`` rad.
        extents: ``[N, 2]`` m, (length, width), constant over time.
        valid: ``[N, T]`` bool, per agent and step.

    Returns:
        ``[T, N, N]`` bool; entry ``[t, i, j]`` is True where agents i and j are both valid at
        step t and their boxes overlap.
    """
    positions = np.asarray(positions, dtype=np.float64)
    yaws = np.asarray(yaws, dtype=np.float64)
    extents = np.asarray(extents, dtype=np.float64)
    ok = present(positions, yaws, extents[:, None], valid)
    centers_t = positions.transpose(1, 0, 2)  # [T, N, 2]
    return _pair_overlap_batched(centers_t, yaws.T, extents, ok.T)


# ---------------------------------------------------------------------- angles and frames
def wrap_angle(angle):
    """Angle [rad] wrapped to [-pi, pi); a float, a numpy array or a torch tensor."""
    return (angle + np.pi) % (2 * np.pi) - np.pi


def to_frame(points: np.ndarray, origin: np.ndarray) -> np.ndarray:
    """World points ``[..., 2]`` m -> the frame ``origin`` ``[3]`` (x m, y m, yaw rad): the
    origin at (0, 0), its heading along +x."""
    c, s = np.cos(origin[2]), np.sin(origin[2])
    rot = np.array([[c, -s], [s, c]])  # columns: the frame's x and y axes in world coordinates
    return (points - origin[:2]) @ rot


def from_frame(points: np.ndarray, origin: np.ndarray) -> np.ndarray:
    """Points ``[..., 2]`` m in the frame ``origin`` ``[3]`` (x m, y m, yaw rad) -> world:
    rotate by the origin's yaw, translate by its position (yaws: ``wrap_angle(yaw +
    origin[2])``)."""
    c, s = np.cos(origin[2]), np.sin(origin[2])
    x, y = points[..., 0], points[..., 1]
    return np.stack([c * x - s * y + origin[0], s * x + c * y + origin[1]], -1)


# ---------------------------------------------------------------------- area
def arc_length(points: np.ndarray) -> np.ndarray:
    """``[P]`` m: cumulative arc length along a polyline of ``[P, 2]`` m points, 0 at the first."""
    return np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(points, axis=0), axis=-1))])


def points_in_area(area: shapely.Geometry, points: np.ndarray) -> np.ndarray:
    """Whether points lie in an area (e.g. the drivable area); the boundary counts as inside.

    Args:
        area: a shapely (Multi)Polygon, m; prepare it once (``shapely.prepare``) for speed.
        points: ``[..., 2]`` m.

    Returns:
        ``[...]`` bool; False for non-finite points and for an empty area.
    """
    points = np.asarray(points, dtype=np.float64)
    flat = points.reshape(-1, 2)
    finite = np.isfinite(flat).all(-1)
    inside = np.zeros(len(flat), dtype=bool)
    if finite.any() and area is not None and not area.is_empty:
        # intersects (not contains): a centre exactly on the road edge is on the road.
        inside[finite] = shapely.intersects_xy(area, flat[finite, 0], flat[finite, 1])
    return inside.reshape(points.shape[:-1])


# ---------------------------------------------------------------------- distance
def box_distance(
    centers_a: np.ndarray,
    yaws_a: np.ndarray,
    extents_a: np.ndarray,
    centers_b: np.ndarray,
    yaws_b: np.ndarray,
    extents_b: np.ndarray,
) -> np.ndarray:
    """Minimum distance between paired oriented boxes (0 when they touch or overlap).

    Args:
        centers_a, centers_b: ``[M, 2]`` m.
        yaws_a, yaws_b: ``[M]`` rad.
        extents_a, extents_b: ``[M, 2]`` m, (length, width); broadcast against the centres.

    Returns:
        ``[M]`` float, m; NaN where any input of a pair is non-finite.
    """
    ca, ya, ea = (np.asarray(x, dtype=np.float64) for x in (centers_a, yaws_a, extents_a))
    cb, yb, eb = (np.asarray(x, dtype=np.float64) for x in (centers_b, yaws_b, extents_b))
    ea, eb = np.broadcast_to(ea, ca.shape), np.broadcast_to(eb, cb.shape)
    ok = present(ca, ya, ea, None) & present(cb, yb, eb, None)
    out = np.full(ok.shape, np.nan)
    if ok.any():
        poly_a = shapely.polygons(box_corners(ca[ok], ya[ok], ea[ok]))
        poly_b = shapely.polygons(box_corners(cb[ok], yb[ok], eb[ok]))
        out[ok] = shapely.distance(poly_a, poly_b)
    return out
