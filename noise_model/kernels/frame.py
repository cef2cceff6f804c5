"""Depth image -> map-frame points with height variance and horizontal covariance, in four compiled stages.

:func:`depth_to_map_points` is the hot path of the mapper: per frame it deprojects every valid pixel,
estimates the incidence angle from block-wise inverse-depth plane fits, finds depth edges and the
windows that hold two surfaces, places speckles at their neighbours' depth
(:func:`noise_model.despeckle`), builds the D435 covariance of :func:`noise_model.point_covariances`,
rotates it into the map frame and adds the first-order pose term of :func:`noise_model.to_map_frame`.
:func:`depth_to_map_points_reference` computes the same thing by composing those public NumPy
functions, and the tests hold the two equal.

The stages (:data:`STAGES`), each a parallel numba kernel in its own module, run in this order on buffers
of the :class:`Workspace`:

1. ``moments`` (:mod:`.planes`): block moments of u', v' and 1 / z, valid pixels per row;
2. ``planes`` (:mod:`.planes`): per block the window's plane, theta, E[g], E[g^2], the mixed-window test;
3. ``edges`` (:mod:`.surfaces`): depth edges and speckles per pixel;
   ``row_medians``, ``surface_medians`` (:mod:`.surfaces`): in windows of two surfaces, the row medians
   and the surface medians;
4. ``points`` (:mod:`.points`): covariances in the camera and map frames, binning, the outputs.

:func:`depth_to_map_points_by_stage` runs them one by one and times each (``elevmap bench``).

numba flags: those of :mod:`noise_model.numba_config` (never ``fastmath=True``, which folds ``isnan`` to
False; no ``arcp``, which changes binning at cell borders). Work is split over image rows or blocks,
each written by one thread only, so the result does not depend on the thread count.
"""

from __future__ import annotations

import time
from typing import NamedTuple

import numpy as np
from numba import njit

from ..checks import check_depth, check_intrinsics, check_pose_cov, check_positive_scalar, check_transform
from ..covariance import point_covariances, to_map_frame
from ..d435 import D435, THETA_GRID, THETA_QUADRATURE, SensorModel, axial_sigma_unchecked
from ..geometry import (
    DEGENERATE_REL, EDGE_JUMP_REL, EDGE_JUMP_SIGMAS, MIXED_WINDOW_Z, NORMAL_MIN_POINTS, ROW_MEDIAN_HALF_PX,
    SURFACE_HALF_ROWS, WINDOW_RADIUS_BLOCKS, default_block_px, deproject, depth_edges, depth_to_metres, despeckle,
    incidence_angle_stats, mixed_windows, plane_depths, surface_depths,
)
from ..numba_config import JIT, resolve_threads, threads
from .compiled import EDGES, PLANES, POINTS, ROW_MEDIANS, SURFACE_MEDIANS, sorting_network
from .planes import moments_stage
from .points import count_outside, points_stage
from .surfaces import surfaces_stage

__all__ = ["MAX_COORDINATE_M", "MAX_DEPTH_M", "MAX_POINT_VARIANCE", "MIN_DEPTH_M", "MIN_HEIGHT_VARIANCE",
           "NOISE_DEPTH_SIGMAS", "STAGES", "MapPoints", "Workspace", "depth_to_map_points",
           "depth_to_map_points_by_stage", "depth_to_map_points_reference"]


_GH_X = np.array(THETA_QUADRATURE[0])
_GH_W = np.array(THETA_QUADRATURE[1])
_GRID_X = np.array(THETA_GRID[0])
_GRID_W = np.array(THETA_GRID[1])

#: sigma_z is evaluated at the local plane's depth when the pixel lies within this many sigma of it.
NOISE_DEPTH_SIGMAS = 3.0

#: Default valid depth range [m]: the D435's minimum range at 848x480 is ~0.2 m; 10 m is the
#: datasheet's upper figure (sigma_z there is ~0.4 m).
MIN_DEPTH_M = 0.1
MAX_DEPTH_M = 10.0

#: The bounds of a point's values that :attr:`MapPoints.n_outside` counts against: coordinates [m] (within
#: 1e9 m of the origin: floor(x / resolution) stays an exact integer), height variance [m^2] (positive,
#: and in m^2 rather than mm^2). They are those a map takes (docs/conventions.md), so that a map can skip
#: its own check of a frame in which the kernel counted none.
MAX_COORDINATE_M = 1e9
MIN_HEIGHT_VARIANCE = 1e-18
MAX_POINT_VARIANCE = 1e4

#: The kernel's stages in the order they run (see the module's docstring).
STAGES = ("moments", "planes", "edges", "row_medians", "surface_medians", "points")


class MapPoints(NamedTuple):
    """One frame's valid points in the map frame, in row-major pixel order.

    Attributes
    ----------
    points_map : ndarray, shape (N, 3) [m]
        z: the map-frame height of the measured point. x, y: where the pixel's ray meets the local
        plane fitted around it (the denoised depth at which sigma_z is evaluated), where that plane
        describes the pixel; else (depth edges, too few neighbours) of the measured point. Why: the
        axial noise moves a point along its ray, so at grazing incidence it lands cells away from
        where its ray met the surface, and which cell a noisy point lands in is correlated with its
        height error (far-landing points are low): binning by the measured point biases the cell
        means and breaks their calibration. The plane's depth carries ~1/N of the pixel's own noise
        (N ~ 400 pixels in the window), so the cell is chosen (almost) independently of the height
        error. In a window that holds more than one surface (:func:`noise_model.mixed_windows`) the
        point is binned at the nearer of the plane's depth and a denoised depth of its own surface,
        the median of the agreeing row medians of 5 rows (:func:`noise_model.surface_depths`; a
        speckle: its replaced depth): a plane fitted across an edge lies beyond the near surface (a box
        top seen at a grazing angle is a strip a few pixels tall, its window mostly the floor behind
        it; a riser and its tread), and binning there carries the near surface's height into the cells
        behind the edge, which its own occlusion leaves sparsely seen; points binned a little too near
        land on cells the camera sees densely, where they are outvoted. The surface median's noise is
        about a fifth of a pixel's, so it bins almost as independently of the height error as the
        plane. Only there: on one surface binning nearer would take the pixels whose noise is negative
        nearer, with their too-high heights, and leave the others, which biases a flat floor.
    height_var : ndarray, shape (N,) [m^2]
        Variance of the map-frame z of each point (Sigma_map[2, 2]). Its axial part is at least the
        squared distance of the pixel from its neighbours' median for a speckle, and from its surface
        median (:func:`noise_model.surface_depths`) in a window of two surfaces: there the window's
        angle and plane are fitted across both surfaces, and the pixels whose noise made the window
        test mixed are among its pixels, so the model's sigma alone understates their noise far from
        the camera.
    horizontal_cov : ndarray, shape (N, 3) [m^2]
        (Sigma_xx, Sigma_xy, Sigma_yy) of each point in the map frame.
    pixel : ndarray, shape (N,), int64
        Flat pixel index v * W + u of each point.
    n_outside : int or None
        How many of the points have a value outside the bounds a map takes: a coordinate not finite or
        beyond :data:`MAX_COORDINATE_M`, a height variance outside [:data:`MIN_HEIGHT_VARIANCE`,
        :data:`MAX_POINT_VARIANCE`] (or NaN), a horizontal covariance with a negative or non-finite xx or
        yy, or a non-finite xy. Counted as the values are written (0: every value is within them, so a map
        need not check them again); None: not counted (points assembled elsewhere, whose values a map
        must check).
    """

    points_map: np.ndarray
    height_var: np.ndarray
    horizontal_cov: np.ndarray
    pixel: np.ndarray
    n_outside: int | None = None


class Workspace:
    """Buffers reused across frames of one image size, so a frame costs no fresh memory.

    Allocating and first touching ~30 MB per 848x480 frame costs more than the arithmetic (page
    faults); a mapper keeps one workspace per camera. Results returned with a workspace are views
    into it, valid until the next call that uses the same workspace.

    Per pixel (H, W): ``row_median``, ``speckle_z``, ``surface_z`` [m] and ``flags`` (uint8), the stages'
    intermediate results (:mod:`noise_model.kernels.surfaces`); per point: the outputs; per block, for the
    block size of the last call: the moments and each pixel column's plane (:meth:`blocks`).
    """

    def __init__(self, height: int, width: int):
        if int(height) < 1 or int(width) < 1:
            raise ValueError(f"workspace size must be positive, got {height}x{width}")
        self.shape = (int(height), int(width))
        H, W = self.shape
        n = H * W
        self.points_map = np.empty((3, n))       # (3, N) storage: contiguous per coordinate
        self.height_var = np.empty(n)
        self.horizontal_cov = np.empty((3, n))
        self.pixel = np.empty(n, dtype=np.int64)
        self.row_median = np.empty(self.shape)  # per pixel of a mixed window: its row median
        self.speckle_z = np.empty(self.shape)   # per speckle: its neighbours' median
        self.surface_z = np.empty(self.shape)   # per pixel of a mixed window: its surface median
        self.flags = np.empty(self.shape, dtype=np.uint8)
        self.rowcount = np.empty(H, dtype=np.int64)
        self.offsets = np.empty(H + 1, dtype=np.int64)
        self.outside = np.empty(H, dtype=np.int64)     # per row: points outside the bounds of MapPoints
        self._block_px = None

    def blocks(self, block_px: int):
        """(M (nby, nbx, 10), columns (7, nby, W)) for blocks of ``block_px``: the block moments and, per
        pixel column of each block row, gain, E[g], E[g^2], alpha, beta, gamma and the mixed flag
        (:func:`noise_model.kernels.planes.planes_block_row`); allocated again only when the block size changes."""
        b = int(block_px)
        if b != self._block_px:
            H, W = self.shape
            nby, nbx = (H + b - 1) // b, (W + b - 1) // b
            self._moments = np.empty((nby, nbx, 10))
            self._columns = np.empty((7, nby, W))
            self._block_px = b
        return self._moments, self._columns


def _stage_calls(d, scale, K, T, P, model, zmin, zmax, b, bin_at_plane, ws, one_by_one=False):
    """The calls of :func:`_frame_kernels` for one frame as (name, regions, (moments, surfaces and points
    arguments)), in order, on the buffers of ``ws``.

    Three parallel regions: ``moments``; the planes, edges and row medians of each block row
    (:func:`noise_model.kernels.surfaces.surfaces_stage`); the surface medians and points of each block row
    (:func:`noise_model.kernels.points.points_stage`). Each boundary is a real dependency: a window's plane
    needs the moments of the block rows around it, a surface median the row medians of the rows around it.
    Without ``one_by_one``: one call, "whole", running the three. ``one_by_one``: one call per stage of
    :data:`STAGES`, each running one region with that stage alone (the same code on the same data, so the
    same result, bit for bit), to time them.
    """
    H, W = d.shape
    fx, fy, cx, cy = K[0, 0], K[1, 1], K[0, 2], K[1, 2]
    up = (np.arange(W) - cx) * (1.0 / fx)       # normalised pixel coordinates u' = (u - cx) / fx per column
    vp = (np.arange(H) - cy) * (1.0 / fy)       # ... and v' = (v - cy) / fy per row
    params = model.params_array()
    family = True if model.family == "disparity" else None     # the family as a type: one compiled loop each
    jump_rel, thr_sig = EDGE_JUMP_REL, EDGE_JUMP_SIGMAS * np.sqrt(2.0)   # the depth-edge threshold's parts
    M, cols = ws.blocks(b)
    gain, eg, eg2, alpha, beta, gamma, mixed = cols
    use_pose = P is not None
    P = np.zeros((6, 6)) if P is None else P
    # the pose term's form as a type (points_stage): None for a diagonal P (or none), True for a full one
    pose_form = None if np.count_nonzero(P - np.diag(np.diag(P))) == 0 else True

    def surfaces(parts):
        return (parts, d, scale, zmin, zmax, params, family, jump_rel, thr_sig, b, M, WINDOW_RADIUS_BLOCKS,
                NORMAL_MIN_POINTS, DEGENERATE_REL, MIXED_WINDOW_Z, _GH_X, _GH_W, _GRID_X, _GRID_W, ROW_MEDIAN_HALF_PX,
                sorting_network(2 * ROW_MEDIAN_HALF_PX + 1), gain, eg, eg2, alpha, beta, gamma, mixed, ws.rowcount,
                ws.flags, ws.speckle_z, ws.row_median)

    def points(parts):
        return (parts, d, scale, zmin, zmax, up, vp, fx, fy, T, P, use_pose, pose_form, params, family,
                NOISE_DEPTH_SIGMAS, b, bool(bin_at_plane), jump_rel, thr_sig, SURFACE_HALF_ROWS,
                sorting_network(2 * SURFACE_HALF_ROWS + 1), ws.row_median, gain, eg, eg2, alpha, beta, gamma, mixed,
                ws.offsets, ws.flags, ws.speckle_z, ws.surface_z, MAX_COORDINATE_M, MIN_HEIGHT_VARIANCE,
                MAX_POINT_VARIANCE, ws.points_map, ws.height_var, ws.horizontal_cov, ws.pixel, ws.outside)

    moments = (d, scale, zmin, zmax, up, vp, b, M, ws.rowcount, ws.offsets)
    if not one_by_one:
        return [("whole", MOMENTS_REGION | SURFACES_REGION | POINTS_REGION,
                 (moments, surfaces(PLANES | EDGES | ROW_MEDIANS), points(SURFACE_MEDIANS | POINTS)))]
    return [("moments", MOMENTS_REGION, (moments, surfaces(0), points(0))),
            ("planes", SURFACES_REGION, (moments, surfaces(PLANES), points(0))),
            ("edges", SURFACES_REGION, (moments, surfaces(EDGES), points(0))),
            ("row_medians", SURFACES_REGION, (moments, surfaces(ROW_MEDIANS), points(0))),
            ("surface_medians", POINTS_REGION, (moments, surfaces(0), points(SURFACE_MEDIANS))),
            ("points", POINTS_REGION, (moments, surfaces(0), points(POINTS)))]


#: Bits of :func:`_frame_kernels`' ``regions``: the moments, the fused surfaces kernel, the fused points kernel.
MOMENTS_REGION = 1
SURFACES_REGION = 2
POINTS_REGION = 4


@njit(**JIT)
def _frame_kernels(regions, moments_args, surfaces_args, points_args):
    """The parallel regions of one frame that ``regions`` names (bits MOMENTS_REGION, SURFACES_REGION,
    POINTS_REGION), in that order, launched from compiled code: (N if the moments ran, else 0; the number of
    points outside the bounds of :class:`MapPoints` if the points ran, else 0).

    Launched from Python, each region waits for a return to the interpreter and the unboxing of its ~40
    arguments before it starts, while OpenMP's worker threads spin only briefly before they sleep
    (:mod:`noise_model.numba_config`) and a sleeping worker must be woken. From here the regions follow
    each other at once. The stages timed one by one run through this same compiled function (one region
    and one part at a time), so that they execute the same machine code as the whole call: compiled into a
    caller, a kernel's arithmetic may be optimised again and differ in the last bit from the kernel
    launched on its own. The thread count is numba's setting at the call (:func:`threads`)."""
    N = 0
    n_out = 0
    if regions & MOMENTS_REGION:
        N = moments_stage(*moments_args)
    if regions & SURFACES_REGION:
        surfaces_stage(*surfaces_args)
    if regions & POINTS_REGION:
        n_out = points_stage(*points_args)
    return N, n_out


def _run_stages(calls, clock=None) -> tuple[int, int]:
    """Run the calls of :func:`_stage_calls` through :func:`_frame_kernels`; with ``clock`` (a dict), its
    entries are the seconds each took. Returns the number of points and the number of them outside the
    bounds of :class:`MapPoints`."""
    N = n_out = 0
    for name, regions, args in calls:
        t0 = time.perf_counter()
        n, o = _frame_kernels(regions, *args)
        if clock is not None:
            clock[name] = time.perf_counter() - t0
        N = n if regions & MOMENTS_REGION else N
        n_out = o if name in ("whole", "points") else n_out
    return int(N), int(n_out)


def _outputs(ws, N, n_out, fresh) -> MapPoints:
    """The first N points of the workspace's outputs (views; ``fresh``: copies of exactly N rows)."""
    arrays = (ws.points_map[:, :N].T, ws.height_var[:N], ws.horizontal_cov[:, :N].T, ws.pixel[:N])
    if fresh:
        arrays = tuple(np.ascontiguousarray(a) for a in arrays)
    return MapPoints(*arrays, n_outside=n_out)


# ---------------------------------------------------------------------------------------------
# public entries
# ---------------------------------------------------------------------------------------------
def _frame_model(model, K) -> SensorModel:
    """The model as it applies to a frame of intrinsics K: a disparity-family model bound to the frame's
    focal length fx (its sigma_d is in pixels of this frame), the paper's family as it is."""
    if not isinstance(model, SensorModel):
        raise ValueError(f"model must be a noise_model.SensorModel, got {type(model).__name__}")
    return model.with_focal(K[0, 0]) if model.family == "disparity" else model


def _prepare(depth, K, T_map_cam, pose_cov, depth_scale, min_depth_m, max_depth_m, block_px):
    d, scale = check_depth(depth, depth_scale)
    K = check_intrinsics(K)
    T = check_transform(T_map_cam)
    P = None if pose_cov is None else check_pose_cov(pose_cov)
    zmin = check_positive_scalar(min_depth_m, "min_depth_m", upper=100.0, unit=" m")
    zmax = check_positive_scalar(max_depth_m, "max_depth_m", upper=100.0, unit=" m")
    if zmin >= zmax:
        raise ValueError(f"min_depth_m ({zmin}) must be below max_depth_m ({zmax})")
    b = default_block_px(d.shape[1]) if block_px is None else int(block_px)
    if b < 1:
        raise ValueError(f"block_px must be >= 1, got {block_px}")
    return d, scale, K, T, P, zmin, zmax, b


def _prepare_frame(depth, K, T_map_cam, pose_cov, depth_scale, model, min_depth_m, max_depth_m, block_px, nthreads,
                   workspace):
    """The checked inputs of one frame (:func:`_prepare`), the model at the frame's focal length, the thread
    count and the workspace (a new one, or the caller's after checking that it fits the depth image)."""
    d, scale, K, T, P, zmin, zmax, b = _prepare(depth, K, T_map_cam, pose_cov, depth_scale, min_depth_m,
                                                max_depth_m, block_px)
    model = _frame_model(model, K)
    n = resolve_threads(nthreads)
    ws = Workspace(*d.shape) if workspace is None else workspace
    if not isinstance(ws, Workspace) or ws.shape != d.shape:
        raise ValueError(f"workspace must be a Workspace of the depth image's size {d.shape}")
    return d, scale, K, T, P, zmin, zmax, b, model, n, ws


def depth_to_map_points(depth, K, T_map_cam, pose_cov=None, *, depth_scale=None, model: SensorModel = D435,
                        min_depth_m: float = MIN_DEPTH_M, max_depth_m: float = MAX_DEPTH_M,
                        block_px: int | None = None, nthreads: int | None = None,
                        workspace: Workspace | None = None, bin_at_plane: bool = True) -> MapPoints:
    """A depth frame's valid points in the map frame with their height variance and horizontal covariance.

    numba, parallel over block rows, in the stages of :data:`STAGES`; equal to
    :func:`depth_to_map_points_reference`.

    Parameters
    ----------
    depth : array_like, shape (H, W)
        uint16 depth units (with ``depth_scale``) or float metres; 0, NaN, inf, negative = no point.
    K : array_like, shape (3, 3)
        Depth-stream intrinsics [px].
    T_map_cam : array_like, shape (4, 4)
        Maps camera-frame points into the map frame.
    pose_cov : array_like, shape (6, 6), optional
        Pose-error covariance, translation [m^2] then rotation [rad^2] in the map frame about the
        camera centre (see :func:`noise_model.to_map_frame`).
    depth_scale : float, optional
        Metres per unit for uint16 depth.
    model : SensorModel
        Noise model (the paper's D435 by default); a disparity-family model's sigma_d is converted to depth
        with this frame's focal length K[0, 0] and the model's baseline.
    min_depth_m, max_depth_m : float
        Valid depth range [m].
    block_px : int, optional
        Normal-estimation block size [px] (see :func:`noise_model.incidence_angles`).
    nthreads : int, optional
        Threads to use (numba's current setting by default).
    workspace : Workspace, optional
        Reused buffers of this image size; the result is then a view into it, valid until the
        workspace's next use. Without one, fresh arrays are returned.
    bin_at_plane : bool
        Place each point's x, y where its ray meets the local plane, or, in a window holding more than
        one surface, at the nearer of that and its surface median (:func:`noise_model.surface_depths`;
        see :class:`MapPoints`); False: at its measured depth.

    Returns
    -------
    MapPoints
    """
    d, scale, K, T, P, zmin, zmax, b, model, n, ws = _prepare_frame(
        depth, K, T_map_cam, pose_cov, depth_scale, model, min_depth_m, max_depth_m, block_px, nthreads, workspace)
    with threads(n):
        N, n_out = _run_stages(_stage_calls(d, scale, K, T, P, model, zmin, zmax, b, bin_at_plane, ws))
    return _outputs(ws, N, n_out, workspace is None)   # without a workspace: fresh arrays, not views


def depth_to_map_points_by_stage(depth, K, T_map_cam, pose_cov=None, *, depth_scale=None,
                                 model: SensorModel = D435, min_depth_m: float = MIN_DEPTH_M,
                                 max_depth_m: float = MAX_DEPTH_M, block_px: int | None = None,
                                 nthreads: int | None = None, workspace: Workspace | None = None,
                                 bin_at_plane: bool = True) -> tuple[MapPoints, dict[str, float]]:
    """:func:`depth_to_map_points` with the wall-clock time of each stage: the same kernels on the same
    buffers, launched one at a time (``elevmap bench`` reports the breakdown).

    Parameters
    ----------
    As :func:`depth_to_map_points`.

    Returns
    -------
    points : MapPoints
        Equal, bit for bit, to :func:`depth_to_map_points` with the same arguments.
    seconds : dict
        {stage: seconds} for each stage of :data:`STAGES`, in order.
    """
    d, scale, K, T, P, zmin, zmax, b, model, n, ws = _prepare_frame(
        depth, K, T_map_cam, pose_cov, depth_scale, model, min_depth_m, max_depth_m, block_px, nthreads, workspace)
    clock: dict[str, float] = {}
    with threads(n):
        N, n_out = _run_stages(_stage_calls(d, scale, K, T, P, model, zmin, zmax, b, bin_at_plane, ws,
                                            one_by_one=True), clock)
    return _outputs(ws, N, n_out, workspace is None), clock


def depth_to_map_points_reference(depth, K, T_map_cam, pose_cov=None, *, depth_scale=None,
                                  model: SensorModel = D435, min_depth_m: float = MIN_DEPTH_M,
                                  max_depth_m: float = MAX_DEPTH_M, block_px: int | None = None,
                                  bin_at_plane: bool = True) -> MapPoints:
    """NumPy reference of :func:`depth_to_map_points`, composed of the public functions.

    depth_to_metres -> deproject -> incidence_angle_stats, plane_depths -> depth_edges, mixed_windows ->
    despeckle -> point_covariances -> to_map_frame.
    """
    d, scale, K, T, P, zmin, zmax, b = _prepare(depth, K, T_map_cam, pose_cov, depth_scale, min_depth_m,
                                                max_depth_m, block_px)
    model = _frame_model(model, K)
    z = depth_to_metres(d, None if d.dtype != np.uint16 else scale, zmin, zmax)
    pts = deproject(z, K)
    theta, theta_std = incidence_angle_stats(pts, block_px=b)
    z_fit = plane_depths(pts, block_px=b)
    left, right = depth_edges(z, model=model, theta=theta)
    mixed = mixed_windows(pts, block_px=b)
    z_row = surface_depths(z, mixed, model=model, theta=theta)
    # a speckle's depth is its neighbours' median, with its distance from them as a variance floor;
    # the planes, angles, edges and surface medians above are those of the measured depths
    z_measured = z
    z, dev2 = despeckle(z, model=model, theta=theta)
    with np.errstate(invalid="ignore"):
        z_row = np.where(z != z_measured, z, z_row)          # a speckle: its replaced depth
        # in a mixed window, the distance from the pixel's surface median is a variance floor too
        dev2 = np.maximum(dev2, np.where(np.isfinite(z_row), (z - z_row) ** 2, 0.0))
    pts = deproject(z, K)
    # sigma_z at the denoised depth where the local plane describes the pixel (within 3 of the smaller
    # of the two sigmas, and inside the valid range), else at the pixel's own depth (edges, where the
    # window holds two surfaces; planes seen edge-on, whose depth runs away)
    with np.errstate(invalid="ignore"):
        zf = np.where(np.isfinite(z_fit) & (z_fit >= zmin) & (z_fit <= zmax), z_fit, z)
        th = np.nan_to_num(theta)
        zz = np.where(np.isfinite(z), z, 1.0)
        s = np.maximum(axial_sigma_unchecked(np.where(np.isfinite(zf), zf, 1.0), th, model),
                       axial_sigma_unchecked(zz, th, model))
        use_fit = np.isfinite(zf) & (np.abs(z - zf) <= NOISE_DEPTH_SIGMAS * s)
    z_noise = np.where(use_fit, zf, z)
    valid = np.isfinite(z)
    pix = np.flatnonzero(valid.ravel())
    p = pts.reshape(-1, 3)[pix]
    cov = point_covariances(p, theta.ravel()[pix], left.ravel()[pix], right.ravel()[pix], fx=K[0, 0],
                            fy=K[1, 1], model=model, z_noise=z_noise.ravel()[pix], theta_std=theta_std.ravel()[pix],
                            min_axial_var=dev2.ravel()[pix])
    cov_map = to_map_frame(cov, p, T, P)
    points_map = p @ T[:3, :3].T + T[:3, 3]
    if bin_at_plane:          # x, y at the local plane (in a mixed window: or the surface median where nearer)
        zn = z_noise.ravel()[pix]
        zb = np.where(mixed.ravel()[pix], np.minimum(zf.ravel()[pix], z_row.ravel()[pix]), zn)
        pb = p * (zb / p[:, 2])[:, None]
        points_map[:, :2] = (pb @ T[:3, :3].T + T[:3, 3])[:, :2]
    hcov = np.stack([cov_map[:, 0, 0], cov_map[:, 0, 1], cov_map[:, 1, 1]], axis=1)
    hvar = cov_map[:, 2, 2].copy()
    n_out = count_outside(points_map, hvar, hcov, MAX_COORDINATE_M, MIN_HEIGHT_VARIANCE, MAX_POINT_VARIANCE)
    return MapPoints(points_map, hvar, hcov, pix.astype(np.int64), n_out)
