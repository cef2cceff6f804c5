"""A physical D435: scene and pose -> projector pattern -> infrared pair -> D4 matcher -> uint16 depth.

Stages (one module each)
------------------------
1. Geometry: the scene is ray cast from the left imager, the right imager (+B along the left
   imager's x axis) and the projector (``noise_model.sim.render_depth``, or any renderer with its
   signature); the imagers at ``supersample`` x ``supersample`` samples per pixel; points and normals
   from the z-depth (:func:`.imagers.surface_geometry`).
2. Materials: albedo of every surface point (:mod:`.materials`): the scene's own materials by
   primitive (a primitive's ``material``, the scene's ``ground_material``; read through the
   renderer's primitive index), then the camera's :class:`.materials.MaterialMap` by position.
3. Projector: irradiance of the dot pattern with inverse-square fall-off, incidence cosine and
   shadows from the projector's own view (:mod:`.projector`); plus a uniform ambient irradiance.
4. Imagers: radiance, relative illumination, lens blur, pixel integration -> noise-free electron
   rates of both images (:meth:`StereoD435.render`, cached by the caller for a static pose); per frame
   auto exposure, shot and read noise, 8-bit output (:meth:`StereoD435.ir_pair`).
5. Matcher: the D4's census/SGM matching with its tests (:mod:`.matcher`), depth z = f B / d in
   1 mm units, 0 = invalid (:meth:`StereoD435.depth`).

Everything random is drawn from the generator the caller passes, in a fixed order (left image, then
right image), so a seed gives the same frames on every run and for any thread count. The dot pattern
and the surface textures are fixed by their own seeds.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Callable, NamedTuple

import numpy as np

from ...numba_config import resolve_threads
from .imagers import Exposure, ImagerModel, auto_exposure, expose, sample_intrinsics, signal_rate
from .imagers import irradiance_rate, surface_geometry, to_map_frame
from .optics import integrate_samples
from .materials import MaterialMap, Texture, Uniform, concrete, white_wall
from .matcher import MatchResult, disparity_to_depth, match, preset
from .projector import Projector, ProjectorView

__all__ = ["StereoD435", "IRScene", "IRFrame"]


class IRScene:
    """Noise-free result of :meth:`StereoD435.render` for one pose (reused for every frame at that pose).

    Attributes
    ----------
    ambient_left, projector_left, ambient_right, projector_right : ndarray, shape (H, W)
        Photo-electron rates [e-/s] of the two imagers from the ambient light and from the projector.
    irradiance_left : ndarray, shape (H, W)
        Mean projector irradiance over each left pixel's samples [W/m^2] (0 where no surface).
    z_true : ndarray, shape (H, W) or None
        Noise-free z-depth at the left pixel centres [m] (NaN = no surface), if asked for.
    T_map_cam : ndarray, shape (4, 4)
        The left imager's pose.
    """

    def __init__(self, ambient_left, projector_left, ambient_right, projector_right, irradiance_left, z_true,
                 T_map_cam):
        self.ambient_left = ambient_left
        self.projector_left = projector_left
        self.ambient_right = ambient_right
        self.projector_right = projector_right
        self.irradiance_left = irradiance_left
        self.z_true = z_true
        self.T_map_cam = T_map_cam

    @property
    def rate_left(self) -> np.ndarray:
        """Total noise-free rate of the left imager [e-/s]."""
        return self.ambient_left + self.projector_left

    @property
    def rate_right(self) -> np.ndarray:
        """Total noise-free rate of the right imager [e-/s]."""
        return self.ambient_right + self.projector_right


class IRFrame(NamedTuple):
    """One simulated frame: the infrared pair, its exposure, the matcher's output and the depth."""

    left: np.ndarray
    right: np.ndarray
    exposure: Exposure
    match: MatchResult
    depth: np.ndarray


def _default_materials() -> MaterialMap:
    return MaterialMap(default=white_wall(), ground=concrete())


@dataclass
class StereoD435:
    """The physical D435 simulation (module docstring).

    Attributes
    ----------
    width, height : int
        Depth mode [px]; must be a size the matcher preset covers (848x480, 424x240, ...).
    K : ndarray, shape (3, 3), optional
        Rectified intrinsics of both imagers [px]; default ``noise_model.D435.intrinsics(width, height)``.
    baseline_m : float
        Right imager at +baseline along the left imager's x axis [m].
    projector : Projector
        Dot pattern and its position.
    imager : ImagerModel
        Radiometry, noise and exposure of both imagers.
    matcher : str or MatcherParams
        Matcher preset ("default", "high_accuracy") or parameters.
    materials : MaterialMap, Uniform or Texture
        Albedo of the surfaces whose primitive names no material of its own (default: white walls and
        boxes, concrete ground); a Uniform or Texture applies to every such surface.
    ambient_w_m2 : float
        Uniform ambient irradiance at 850 nm on every surface [W/m^2] (0: projector only).
    shadow_scale : float
        Size of the projector's shadow render relative to the image.
    max_range_m : float
        Surfaces farther than this are not rendered [m].
    depth_unit_m : float
        Depth unit of the output (0.001).
    renderer : callable, optional
        ``renderer(scene, K, width, height, T_map_cam) -> (z, theta)``; default
        ``noise_model.sim.render_depth``. For a scene that carries materials it is called with
        ``return_index=True`` and must then also return the primitive index (as ``render_depth``).
    nthreads : int, optional
        numba threads; results do not depend on it.
    """

    width: int = 848
    height: int = 480
    K: np.ndarray | None = None
    baseline_m: float = 0.050
    projector: Projector = field(default_factory=Projector)
    imager: ImagerModel = field(default_factory=ImagerModel)
    matcher: object = "default"
    materials: MaterialMap = field(default_factory=_default_materials)
    ambient_w_m2: float = 0.0
    shadow_scale: float = 1.0
    max_range_m: float = 10.0
    depth_unit_m: float = 0.001
    renderer: Callable | None = None
    nthreads: int | None = None

    def __post_init__(self):
        self.matcher = preset(self.matcher)
        if isinstance(self.width, bool) or int(self.width) != self.width or isinstance(self.height, bool) \
                or int(self.height) != self.height:
            raise ValueError(f"image size must be integers, got {self.width!r} x {self.height!r}")
        self.width, self.height = int(self.width), int(self.height)
        self.matcher.check_size(self.width, self.height)
        if self.K is None:
            from ...d435 import D435

            self.K = D435.intrinsics(self.width, self.height)
        K = np.asarray(self.K, dtype=np.float64)
        if K.shape != (3, 3) or not (K[0, 0] > 0 and K[1, 1] > 0) or not np.all(np.isfinite(K)):
            raise ValueError("K must be a finite 3x3 camera matrix with positive focal lengths")
        self.K = K
        for name in ("baseline_m", "shadow_scale", "max_range_m", "depth_unit_m"):
            v = getattr(self, name)
            if not (isinstance(v, (int, float)) and math.isfinite(v) and v > 0):
                raise ValueError(f"{name} must be finite and > 0, got {v!r}")
        if not (isinstance(self.ambient_w_m2, (int, float)) and math.isfinite(self.ambient_w_m2)
                and self.ambient_w_m2 >= 0):
            raise ValueError(f"ambient_w_m2 must be finite and >= 0, got {self.ambient_w_m2!r}")
        if not isinstance(self.projector, Projector):
            raise ValueError(f"projector must be a Projector, got {type(self.projector).__name__}")
        if not isinstance(self.imager, ImagerModel):
            raise ValueError(f"imager must be an ImagerModel, got {type(self.imager).__name__}")
        if isinstance(self.materials, (Uniform, Texture)):
            self.materials = MaterialMap(default=self.materials, ground=None)
        if not isinstance(self.materials, MaterialMap):
            raise ValueError(f"materials must be a MaterialMap, Uniform or Texture, "
                             f"got {type(self.materials).__name__}")
        self.nthreads = resolve_threads(self.nthreads)
        self._workspace = {}                      # the matcher's volumes, reused from frame to frame
        self._buffers = {}                        # the renderer's per-sample arrays, reused likewise

    # -- geometry -------------------------------------------------------------------------------
    @property
    def focal_px(self) -> float:
        return float(self.K[0, 0])

    def right_pose(self, T_map_cam) -> np.ndarray:
        """T_map_right (4, 4): the left pose moved by +baseline along its x axis."""
        T = np.eye(4)
        T[0, 3] = self.baseline_m
        return np.asarray(T_map_cam, dtype=np.float64) @ T

    def _render(self, scene, K, width, height, T, return_index: bool = False):
        if self.renderer is None:
            from ..render import render_depth

            return render_depth(scene, K, width, height, T, max_range_m=self.max_range_m, nthreads=self.nthreads,
                                return_index=return_index)
        if return_index:
            return self.renderer(scene, K, width, height, T, return_index=True)
        return self.renderer(scene, K, width, height, T)

    def _buffer(self, name: str, shape) -> np.ndarray | None:
        """A float64 buffer kept between renders (fresh memory is slow to touch), or None the first time."""
        buf = self._buffers.get(name)
        if buf is None or buf.shape != tuple(shape):
            buf = self._buffers[name] = np.empty(shape)
        return buf

    def _imager_rates(self, scene, T_map_i, x_cam_m, view, with_irradiance=False):
        """Ambient and projector electron rates (H, W) of one imager at x_cam_m along the left x axis."""
        s = self.imager.supersample
        Ks = sample_intrinsics(self.K, s)
        own = bool(getattr(scene, "has_materials", False))        # the scene's materials need the primitive index
        z, _, *index = self._render(scene, Ks, self.width * s, self.height * s, T_map_i, return_index=own)
        z = np.ascontiguousarray(z, dtype=np.float64)
        hs, ws = z.shape
        hit = bool(np.isfinite(z).any())
        pts, nrm = surface_geometry(z, Ks, self.nthreads,
                                    out=(self._buffer("pts", (hs, ws, 3)), self._buffer("nrm", (hs, ws, 3))))
        p = pts.reshape(-1, 3)
        n = nrm.reshape(-1, 3)
        # map frame for the materials; p then moves from the camera frame into the projector frame
        p_map, n_map = to_map_frame(p, n, T_map_i, self.nthreads,
                                    out=(self._buffer("p_map", p.shape), self._buffer("n_map", n.shape)),
                                    shift_x_m=x_cam_m - self.projector.offset_m)
        albedo = self.materials.evaluate(p_map, n_map, self.nthreads, out=self._buffer("albedo", (hs * ws,)),
                                         index=index[0].reshape(-1) if own else None,
                                         scene=scene if own else None).reshape(hs, ws)
        e_proj = self.projector.irradiance(p, n, occlusion=view, nthreads=self.nthreads,
                                           out=self._buffer("e_proj", (hs * ws,))).reshape(hs, ws)
        # e-/s per W/m^2 of irradiance at each sample (0 where there is no surface)
        per_irr = signal_rate(albedo, 1.0, Ks, self.focal_px, self.imager, self.nthreads,
                              out=self._buffer("per_irr", (hs, ws)))
        blur = self.imager.blur_sigma_native_px * self.focal_px / self.imager.native_focal_px
        rate_samples = irradiance_rate(per_irr, e_proj, self.nthreads, out=self._buffer("rate", (hs, ws)))
        e_pix = integrate_samples(e_proj, s, 0.0, self.nthreads) if with_irradiance else None   # NaN now 0
        rate_p = integrate_samples(rate_samples, s, blur, self.nthreads)
        rate_a = integrate_samples(per_irr * self.ambient_w_m2, s, blur, self.nthreads) if self.ambient_w_m2 > 0 \
            else np.zeros_like(rate_p)
        return rate_a, rate_p, e_pix, hit

    def render(self, scene, T_map_cam, with_truth: bool = False) -> IRScene:
        """Noise-free electron rates of both imagers for one pose (stages 1-4 without noise).

        Parameters
        ----------
        scene : noise_model.sim.Scene
            The terrain (map frame).
        T_map_cam : array_like, shape (4, 4)
            Pose of the left imager (x right, y down, z forward) in the map frame.
        with_truth : bool
            Also render the noise-free z-depth at the left pixel centres.

        Raises
        ------
        ValueError
            If no surface of the scene is in view of the left imager.
        """
        from ...checks import check_transform

        T = check_transform(T_map_cam, "T_map_cam")
        wv = max(2, int(round(self.width * self.shadow_scale)))
        hv = max(2, int(round(self.height * self.shadow_scale)))
        Kv = self.projector.view_intrinsics(wv, hv)
        zv, _ = self._render(scene, Kv, wv, hv, self.projector.pose_in_map(T))
        view = ProjectorView(np.asarray(zv, dtype=np.float64), Kv)
        amb_l, proj_l, e_l, hit = self._imager_rates(scene, T, 0.0, view, with_irradiance=True)
        if not hit:
            raise ValueError(f"the scene has no surface in view of the left imager within max_range_m = "
                             f"{self.max_range_m} m (no ray hit anything)")
        amb_r, proj_r, _, _ = self._imager_rates(scene, self.right_pose(T), self.baseline_m, view)
        z_true = None
        if with_truth:
            z_true, _ = self._render(scene, self.K, self.width, self.height, T)
        return IRScene(amb_l, proj_l, amb_r, proj_r, e_l, z_true, T)

    # -- per frame -------------------------------------------------------------------------------
    def ir_pair(self, ir: IRScene, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray, Exposure]:
        """One noisy infrared pair (left, right) at the auto (or manual) exposure of the left image."""
        exposure = auto_exposure(ir.rate_left, self.imager)
        c = self.projector.speckle_contrast
        left = expose(ir.ambient_left, ir.projector_left, exposure, rng, self.imager, c, self.focal_px, self.nthreads)
        right = expose(ir.ambient_right, ir.projector_right, exposure, rng, self.imager, c, self.focal_px,
                       self.nthreads)
        return left, right, exposure

    def depth(self, left, right) -> tuple[np.ndarray, MatchResult]:
        """The D4 matcher on a pair: depth (H, W) uint16 in depth units (0 = invalid) and the match."""
        res = match(left, right, self.matcher, self.nthreads, self._workspace)
        return disparity_to_depth(res.disparity, self.focal_px, self.baseline_m, self.depth_unit_m), res

    def frame(self, ir: IRScene, rng: np.random.Generator) -> IRFrame:
        """One frame from a rendered pose: fresh sensor noise, the same scene and dots."""
        left, right, exposure = self.ir_pair(ir, rng)
        depth, res = self.depth(left, right)
        return IRFrame(left, right, exposure, res, depth)

    def depth_frame(self, scene, T_map_cam, rng: np.random.Generator) -> np.ndarray:
        """One depth frame (H, W) uint16 of a camera at ``T_map_cam``: rendered there, fresh noise.

        The frames of a moving camera (a walk); ``rng`` gives this frame's sensor noise.
        """
        return self.frame(self.render(scene, T_map_cam), rng).depth

    def frames(self, scene, T_map_cam, n_frames: int, rng) -> np.ndarray:
        """``n_frames`` depth frames (n, H, W) uint16 of a static camera; rendered once, noise per frame.

        ``rng`` is a numpy Generator or a seed.
        """
        if isinstance(n_frames, bool) or int(n_frames) != n_frames or n_frames < 1:
            raise ValueError(f"n_frames must be an integer >= 1, got {n_frames!r}")
        gen = rng if isinstance(rng, np.random.Generator) else np.random.default_rng(rng)
        ir = self.render(scene, T_map_cam)
        return np.stack([self.frame(ir, gen).depth for _ in range(int(n_frames))])

    @property
    def min_depth_m(self) -> float:
        """Nearest measurable depth [m]: f B / (D - 1.5), the winner at most D - 2 plus half a pixel."""
        return self.focal_px * self.baseline_m / (self.matcher.n_disp - 1.5)
