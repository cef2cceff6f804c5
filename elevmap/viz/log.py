"""Logging the map's world to rerun: frames, cameras, depth, points, covariance ellipsoids, scalars,
text, images and the height mesh.

The functions take plain NumPy arrays plus an entity path and never import the mapping or noise-model
internals, so the maths stays testable without rerun and this package can follow rerun's API changes
alone (rerun-sdk 0.41 is pinned: it renames its API every minor release).

Frames and entity paths
-----------------------
Entity paths mirror frames: data logged at an entity is expressed in that entity's frame.

* ``world``: the map frame, right-handed, z up (:func:`log_world_frame`), in metres.
* ``world/camera_<i>``: a camera frame (RealSense/OpenCV: x right, y down, z forward), placed by a
  ``Transform3D`` holding ``T_world_cam`` (maps camera-frame points into ``world``).
* ``world/camera_<i>/depth``: the pinhole (intrinsics, ``camera_xyz=RDF``) and its depth image.
* ``plots/<name>``: static 2-D charts (:mod:`elevmap.viz.charts`) or time series of scalars.
"""

from __future__ import annotations

import numpy as np
import rerun as rr
from scipy.spatial.transform import Rotation

__all__ = [
    "log_world_frame",
    "log_transform",
    "log_camera",
    "log_depth",
    "log_depth_png",
    "log_points",
    "ellipsoid_parameters",
    "log_covariance_ellipsoids",
    "set_time",
    "log_scalar",
    "log_text",
    "log_rgb_image",
    "map_image",
    "log_height_mesh",
    "log_trail",
    "log_exact",
]


# ---------------------------------------------------------------------------------------------
# Frames, cameras and images
# ---------------------------------------------------------------------------------------------
def log_world_frame(rec: rr.RecordingStream, entity: str = "world") -> None:
    """Declare ``entity`` a right-handed, z-up frame (the map frame), static."""
    rec.log(entity, rr.ViewCoordinates.RIGHT_HAND_Z_UP, static=True)


def _as_transform(T, name: str) -> np.ndarray:
    T = np.asarray(T, dtype=np.float64)
    if T.shape != (4, 4) or not np.all(np.isfinite(T)):
        raise ValueError(f"{name} must be a finite 4x4 homogeneous transform, got shape {T.shape}")
    R = T[:3, :3]
    if np.abs(R @ R.T - np.eye(3)).max() > 1e-6 or np.linalg.det(R) <= 0:
        raise ValueError(f"{name} rotation part is not a proper rotation")
    return T


def log_transform(rec: rr.RecordingStream, entity: str, T_parent_child, static: bool = False) -> None:
    """Place the frame ``entity`` in its parent's frame.

    Parameters
    ----------
    T_parent_child : array_like, shape (4, 4)
        Maps points of the child frame (``entity``) into the parent frame: p_parent = R p_child + t
        (t [m]). Stored by rerun as float32 translation + quaternion (x, y, z, w).
    static : bool
        Log as static (timeless) data.
    """
    T = _as_transform(T_parent_child, "T_parent_child")
    q_xyzw = Rotation.from_matrix(T[:3, :3]).as_quat()
    rec.log(entity, rr.Transform3D(translation=T[:3, 3], quaternion=q_xyzw), static=static)


def log_camera(rec: rr.RecordingStream, entity: str, K, width: int, height: int, T_parent_cam=None,
               static: bool = True, image_plane_distance: float | None = None) -> None:
    """Log a pinhole camera (RealSense/OpenCV axes: x right, y down, z forward = RDF).

    Parameters
    ----------
    entity : str
        Where the pinhole goes, e.g. ``world/camera_0/depth``; log the depth image there too.
    K : array_like, shape (3, 3)
        Intrinsics [px] (fx, fy, cx, cy; pixel-centre convention).
    width, height : int
        Image size [px].
    T_parent_cam : array_like, shape (4, 4), optional
        Pose of the camera in the parent entity's frame (p_parent = R p_cam + t, t [m]); when given
        it is logged at ``entity`` as a Transform3D (applied before the pinhole).
    static : bool
        Calibration is static by default.
    image_plane_distance : float, optional
        Size of the drawn frustum [m].
    """
    K = np.asarray(K, dtype=np.float64)
    if K.shape != (3, 3) or not np.all(np.isfinite(K)) or K[0, 0] <= 0 or K[1, 1] <= 0:
        raise ValueError(f"K must be a finite 3x3 camera matrix with fx, fy > 0, got {K!r}")
    if T_parent_cam is not None:
        log_transform(rec, entity, T_parent_cam, static=static)
    rec.log(entity, rr.Pinhole(image_from_camera=K, resolution=[int(width), int(height)],
                               camera_xyz=rr.ViewCoordinates.RDF, image_plane_distance=image_plane_distance),
            static=static)


def log_depth(rec: rr.RecordingStream, entity: str, depth, meter: float | None = None,
              depth_range: tuple[float, float] | None = None, static: bool = False) -> None:
    """Log a depth image under a pinhole.

    Parameters
    ----------
    depth : array_like, shape (H, W)
        uint16 depth units (0 = no data; give ``meter``) or float metres (NaN/inf/<= 0 = no data).
    meter : float, optional
        Depth units per metre, e.g. 1000 for a D435 at its default 1 mm scale (= 1 / depth_scale).
        Ignored (1.0) for float metres.
    depth_range : (float, float), optional
        Colour-map range in depth units of the logged image.
    static : bool
        Log as static data.
    """
    d = np.asarray(depth)
    if d.ndim != 2:
        raise ValueError(f"depth must be a 2-D image (H, W), got shape {d.shape}")
    if np.issubdtype(d.dtype, np.integer):
        if meter is None:
            raise ValueError("integer depth needs meter= (depth units per metre, 1000 for 1 mm units)")
        img = d
    elif np.issubdtype(d.dtype, np.floating):
        img = np.where(np.isfinite(d) & (d > 0), d, 0.0).astype(np.float32)
        meter = 1.0
    else:
        raise ValueError(f"depth must be integer units or float metres, got dtype {d.dtype}")
    rec.log(entity, rr.DepthImage(img, meter=float(meter), depth_range=depth_range), static=static)


def log_points(rec: rr.RecordingStream, entity: str, points, colors=None, radii=None,
               static: bool = False) -> None:
    """Log 3-D points.

    Parameters
    ----------
    points : array_like, shape (N, 3)
        Points [m] in the frame of ``entity``; rows with non-finite values are dropped.
    colors : array_like, shape (N, 3) or (N, 4) uint8, or (3,)/(4,), optional
    radii : float or array_like, shape (N,), optional
        Point radii [m].
    """
    p = np.asarray(points, dtype=np.float64)
    if p.ndim != 2 or p.shape[1] != 3:
        raise ValueError(f"points must have shape (N, 3), got {p.shape}")
    keep = np.isfinite(p).all(axis=1)
    c = None
    if colors is not None:
        c = np.asarray(colors)
        if c.ndim == 2:
            if c.shape[0] != len(p):
                raise ValueError(f"colors must have one row per point ({len(p)}), got {c.shape}")
            c = c[keep]
    r = None
    if radii is not None:
        r = np.asarray(radii, dtype=np.float32)
        if r.ndim == 1:
            if r.shape[0] != len(p):
                raise ValueError(f"radii must have one value per point ({len(p)}), got {r.shape}")
            r = r[keep]
    rec.log(entity, rr.Points3D(p[keep].astype(np.float32), colors=c, radii=r), static=static)


def ellipsoid_parameters(covs, n_sigma: float = 2.0) -> tuple[np.ndarray, np.ndarray]:
    """Half sizes and orientations of the n-sigma ellipsoids of 3x3 covariances.

    Parameters
    ----------
    covs : array_like, shape (N, 3, 3)
        Symmetric positive semi-definite covariances [m^2].
    n_sigma : float
        Scale: half sizes are n_sigma standard deviations along the principal axes.

    Returns
    -------
    half_sizes : ndarray, shape (N, 3) [m]
        n_sigma sqrt(eigenvalues) (negative round-off eigenvalues clipped to 0).
    quaternions_xyzw : ndarray, shape (N, 4)
        Rotations whose columns are the eigenvectors (made proper rotations, det = +1), so
        cov = R diag((half_sizes / n_sigma)^2) R^T.
    """
    C = np.asarray(covs, dtype=np.float64)
    if C.ndim != 3 or C.shape[1:] != (3, 3):
        raise ValueError(f"covs must have shape (N, 3, 3), got {C.shape}")
    if not np.all(np.isfinite(C)):
        raise ValueError("covs has non-finite entries")
    if len(C) == 0:
        return np.zeros((0, 3)), np.zeros((0, 4))
    ev, evec = np.linalg.eigh(0.5 * (C + np.swapaxes(C, 1, 2)))
    evec = evec.copy()
    evec[np.linalg.det(evec) < 0, :, 0] *= -1.0
    half = float(n_sigma) * np.sqrt(np.clip(ev, 0.0, None))
    return half, Rotation.from_matrix(evec).as_quat()


def log_covariance_ellipsoids(rec: rr.RecordingStream, entity: str, centers, covs, n_sigma: float = 2.0,
                              colors=None, fill_mode: str = "solid", static: bool = False) -> None:
    """Log the n-sigma ellipsoids of per-point covariances.

    Parameters
    ----------
    centers : array_like, shape (N, 3)
        Ellipsoid centres [m] in the frame of ``entity``.
    covs : array_like, shape (N, 3, 3)
        Covariances [m^2] expressed in the same frame.
    n_sigma : float
        Half sizes are ``n_sigma`` standard deviations (2: about 74 % of a 3-D Gaussian's mass).
    colors : array_like, shape (N, 3) uint8 or (3,), optional
    fill_mode : {"solid", "major_wireframe", "dense_wireframe"}
    """
    c = np.asarray(centers, dtype=np.float64)
    if c.ndim != 2 or c.shape[1] != 3:
        raise ValueError(f"centers must have shape (N, 3), got {c.shape}")
    if np.asarray(covs).shape[:1] != (len(c),):
        raise ValueError(f"covs must have shape ({len(c)}, 3, 3), got {np.asarray(covs).shape}")
    half, q = ellipsoid_parameters(covs, n_sigma)
    rec.log(entity, rr.Ellipsoids3D(centers=c.astype(np.float32), half_sizes=half.astype(np.float32),
                                    quaternions=q.astype(np.float32), colors=colors, fill_mode=fill_mode),
            static=static)


# ---------------------------------------------------------------------------------------------
# Scalars, time and text
# ---------------------------------------------------------------------------------------------
def set_time(rec: rr.RecordingStream, timeline: str, *, sequence: int | None = None,
             seconds: float | None = None, timestamp_ns: int | None = None) -> None:
    """Set the current time of ``timeline``: a frame index, a duration [s] or a timestamp [ns]."""
    given = [x is not None for x in (sequence, seconds, timestamp_ns)]
    if sum(given) != 1:
        raise ValueError("give exactly one of sequence, seconds, timestamp_ns")
    if sequence is not None:
        rec.set_time(timeline, sequence=int(sequence))
    elif seconds is not None:
        rec.set_time(timeline, duration=float(seconds))
    else:
        rec.set_time(timeline, timestamp=np.datetime64(int(timestamp_ns), "ns"))


def log_scalar(rec: rr.RecordingStream, entity: str, value) -> None:
    """Log one scalar (or a few, one per series) at the current time, for a time-series plot."""
    rec.log(entity, rr.Scalars(np.atleast_1d(np.asarray(value, dtype=np.float64))))


def log_text(rec: rr.RecordingStream, entity: str, markdown: str, static: bool = True) -> None:
    """Log a Markdown note (shown by a text-document view)."""
    rec.log(entity, rr.TextDocument(markdown, media_type=rr.MediaType.MARKDOWN), static=static)


# ---------------------------------------------------------------------------------------------
# Map views: images of layers, the height mesh, the trail, exact values
# ---------------------------------------------------------------------------------------------
def log_rgb_image(rec: rr.RecordingStream, entity: str, rgb, static: bool = False) -> None:
    """Log an RGB image (H, W, 3) uint8, e.g. a map layer coloured with :func:`colormap`."""
    a = np.asarray(rgb)
    if a.ndim != 3 or a.shape[2] != 3 or a.dtype != np.uint8:
        raise ValueError(f"rgb must be an (H, W, 3) uint8 image, got {a.dtype} {a.shape}")
    rec.log(entity, rr.Image(np.ascontiguousarray(a), color_model="RGB"), static=static)


def map_image(layer) -> np.ndarray:
    """A map layer in map-index order (i along +x, j along +y) as an image seen from above with +x up
    and +y to the left: ``layer[::-1, ::-1]`` (row 0 = largest x, column 0 = largest y)."""
    a = np.asarray(layer)
    if a.ndim < 2:
        raise ValueError(f"layer must be at least 2-D, got shape {a.shape}")
    return a[::-1, ::-1]



def log_height_mesh(rec: rr.RecordingStream, entity: str, x_centres, y_centres, height, colors,
                    static: bool = False) -> int:
    """Log a height field as a triangle mesh over its known cells.

    Parameters
    ----------
    x_centres, y_centres : array_like, shape (n,), (m,)
        Cell-centre coordinates of rows and columns [m], map frame.
    height : array_like, shape (n, m)
        Height per cell [m]; NaN cells are left out (a quad needs its four corners known).
    colors : array_like, shape (n, m, 3), uint8
        Colour per cell.

    Returns
    -------
    int
        Number of triangles logged.
    """
    h = np.asarray(height, dtype=np.float64)
    xs, ys = np.asarray(x_centres, dtype=np.float64), np.asarray(y_centres, dtype=np.float64)
    if h.shape != (len(xs), len(ys)):
        raise ValueError(f"height must have shape ({len(xs)}, {len(ys)}), got {h.shape}")
    c = np.asarray(colors, dtype=np.uint8).reshape(h.size, -1)
    X, Y = np.meshgrid(xs, ys, indexing="ij")
    known = np.isfinite(h)
    quad = known[:-1, :-1] & known[1:, :-1] & known[:-1, 1:] & known[1:, 1:]
    if not quad.any():
        rec.log(entity, rr.Clear(recursive=False), static=static)
        return 0
    n, m = h.shape
    idx = np.arange(n * m).reshape(n, m)
    a, b, cc, d = idx[:-1, :-1][quad], idx[1:, :-1][quad], idx[:-1, 1:][quad], idx[1:, 1:][quad]
    tris = np.concatenate([np.stack([a, b, d], 1), np.stack([a, d, cc], 1)])
    used, inverse = np.unique(tris, return_inverse=True)
    verts = np.column_stack([X.ravel()[used], Y.ravel()[used], np.nan_to_num(h.ravel()[used])]).astype(np.float32)
    rec.log(entity, rr.Mesh3D(vertex_positions=verts, triangle_indices=inverse.reshape(-1, 3).astype(np.uint32),
                              vertex_colors=c[used]), static=static)
    return int(len(tris))


def log_trail(rec: rr.RecordingStream, entity: str, positions, color=(255, 200, 0), radius: float = 0.01) -> None:
    """The path travelled so far as one line strip; positions (K, 3) [m], map frame."""
    p = np.asarray(positions, dtype=np.float32)
    if p.ndim != 2 or p.shape[1] != 3:
        raise ValueError(f"positions must have shape (K, 3), got {p.shape}")
    rec.log(entity, rr.LineStrips3D([p], colors=[color], radii=[radius]))


def log_exact(rec: rr.RecordingStream, entity: str, static: bool = False, **arrays) -> None:
    """Log float64 arrays losslessly as ``AnyValues`` (rerun's transforms and pinholes are float32).

    The project's own recordings keep each frame's K, pose, pose covariance, stamp and depth scale
    here, so that a replay reproduces the mapped frames bit for bit.
    """
    values = {k: np.atleast_1d(np.asarray(v, dtype=np.float64)).ravel() for k, v in arrays.items() if v is not None}
    rec.log(entity, rr.AnyValues(**values), static=static)


def log_depth_png(rec: rr.RecordingStream, entity: str, depth_u16, meter: float, static: bool = False) -> None:
    """Log uint16 depth losslessly PNG-compressed (``EncodedDepthImage``, encoded by rerun itself); about half
    the size of raw noisy depth and a tenth of smooth depth. ``meter``: depth units per metre (1000 for 1 mm).

    The fastest zlib level (1) is used: higher levels shrink noisy depth by a few per cent at several
    times the encoding time per frame.
    """
    d = np.asarray(depth_u16)
    if d.dtype != np.uint16 or d.ndim != 2:
        raise ValueError(f"depth must be a 2-D uint16 image, got {d.dtype} {d.shape}")
    encoded = rr.DepthImage(np.ascontiguousarray(d), meter=float(meter)).compress(compress_level=1)
    if not isinstance(encoded, rr.EncodedDepthImage):
        raise ValueError("PNG encoding of the depth image failed")
    rec.log(entity, encoded, static=static)
