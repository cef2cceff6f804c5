"""A transform buffer like tf2's: static and time-stamped edges of a frame tree, looked up at a stamp.

Each edge ``parent -> child`` is ``T_parent_child`` (what a ``geometry_msgs/TransformStamped`` with
``header.frame_id = parent`` and ``child_frame_id = child`` holds: child-frame points into the parent
frame). :meth:`TfBuffer.lookup` composes the chain between two frames through their common ancestor,
each time-stamped edge interpolated at the stamp (translation linear in time, rotation by slerp).

Extrapolation rule: a stamp before an edge's first or after its last sample is served by that end
sample only within ``tolerance`` [s] (default :data:`TF_TOLERANCE_S`); further out the lookup fails
with :class:`TransformUnavailable`, as tf2 refuses to extrapolate. The tolerance covers the usual
offset between a camera's stamp and the nearest transform at the ends of a recording, and is small
against the motion of a walking robot over it (0.5 m/s moves 5 mm in 10 ms).
"""

from __future__ import annotations

from collections import defaultdict

import numpy as np

from noise_model.checks import check_transform

from ..sources.poses import PoseTrack

__all__ = ["TfBuffer", "TransformUnavailable", "TF_TOLERANCE_S"]

#: Longest hold of an edge's end sample beyond its recorded span [s].
TF_TOLERANCE_S = 0.01


class TransformUnavailable(LookupError, ValueError):
    """No transform between two frames at a stamp: frames not connected, or the stamp outside an edge's span."""


class TfBuffer:
    """Static and dynamic transforms of one frame tree.

    Parameters
    ----------
    tolerance : float
        Extrapolation tolerance [s] (see the module docstring).

    Notes
    -----
    Add every sample first, then look up: the tracks are built on the first lookup after an addition.
    A frame has one parent; a child given a second parent is an error, as in tf2.
    """

    def __init__(self, tolerance: float = TF_TOLERANCE_S):
        tol = float(tolerance)
        if not np.isfinite(tol) or tol < 0:
            raise ValueError(f"tolerance must be finite and >= 0 s, got {tolerance!r}")
        self.tolerance = tol
        self._parent: dict[str, str] = {}
        self._static: dict[str, np.ndarray] = {}
        self._samples: dict[str, dict[float, np.ndarray]] = defaultdict(dict)
        self._tracks: dict[str, PoseTrack] = {}

    def _set_parent(self, parent: str, child: str) -> None:
        parent, child = str(parent).lstrip("/"), str(child).lstrip("/")
        if not parent or not child or parent == child:
            raise ValueError(f"a transform needs two different frame names, got {parent!r} -> {child!r}")
        old = self._parent.get(child)
        if old is not None and old != parent:
            raise ValueError(f"frame {child!r} has two parents, {old!r} and {parent!r}")
        self._parent[child] = parent

    def add_static(self, parent: str, child: str, T_parent_child) -> None:
        """Add a static edge (``/tf_static``); a later one for the same child replaces it."""
        T = check_transform(T_parent_child, f"transform {parent} -> {child}")
        self._set_parent(parent, child)
        child = str(child).lstrip("/")
        if child in self._samples:
            raise ValueError(f"frame {child!r} is both static and time-stamped")
        self._static[child] = T

    def add(self, parent: str, child: str, stamp: float, T_parent_child) -> None:
        """Add a time-stamped sample of an edge (``/tf``); a repeated stamp replaces the sample."""
        T = check_transform(T_parent_child, f"transform {parent} -> {child}")
        s = float(stamp)
        if not np.isfinite(s):
            raise ValueError(f"transform {parent} -> {child}: stamp {stamp!r} is not finite")
        self._set_parent(parent, child)
        child = str(child).lstrip("/")
        if child in self._static:
            raise ValueError(f"frame {child!r} is both static and time-stamped")
        self._samples[child][s] = T
        self._tracks.pop(child, None)

    @property
    def frames(self) -> set[str]:
        """Every frame named by an edge."""
        return set(self._parent) | set(self._parent.values())

    def parent(self, frame: str) -> str | None:
        return self._parent.get(str(frame).lstrip("/"))

    def span(self, frame: str) -> tuple[float, float] | None:
        """(first, last) stamp [s] of the time-stamped edge into ``frame``; None for a static edge or a root."""
        samples = self._samples.get(str(frame).lstrip("/"))
        return (min(samples), max(samples)) if samples else None

    def _chain(self, frame: str) -> list[str]:
        """``frame`` and its ancestors up to the root."""
        out = [frame]
        while out[-1] in self._parent:
            out.append(self._parent[out[-1]])
            if len(out) > len(self._parent) + 1:
                raise ValueError(f"the transform tree has a cycle through {frame!r}")
        return out

    def _edge(self, child: str, stamp: float) -> np.ndarray:
        if child in self._static:
            return self._static[child]
        track = self._tracks.get(child)
        if track is None:
            samples = self._samples[child]
            stamps = np.array(sorted(samples))
            track = PoseTrack(np.stack([samples[s] for s in stamps]), stamps,
                              source=f"transform {self._parent[child]} -> {child}")
            self._tracks[child] = track
        try:
            return track.at(stamp, tolerance=self.tolerance)[0]
        except ValueError as exc:
            raise TransformUnavailable(str(exc)) from None

    def can_connect(self, target: str, source: str) -> bool:
        """Whether the two frames are in one tree (whatever the stamp)."""
        target, source = str(target).lstrip("/"), str(source).lstrip("/")
        return target == source or self._chain(target)[-1] == self._chain(source)[-1]

    def path(self, target: str, source: str) -> list[str]:
        """The frames from ``target`` to ``source`` through their common ancestor (a ValueError when not connected)."""
        target, source = str(target).lstrip("/"), str(source).lstrip("/")
        if not self.can_connect(target, source):
            raise TransformUnavailable(f"frames {target!r} and {source!r} are not connected")
        up_t, up_s = self._chain(target), self._chain(source)
        common = next(f for f in up_s if f in set(up_t))
        return up_t[: up_t.index(common) + 1] + list(reversed(up_s[: up_s.index(common)]))

    def root(self, frame: str) -> str:
        """The root of ``frame``'s tree."""
        return self._chain(str(frame).lstrip("/"))[-1]

    def lookup(self, target: str, source: str, stamp: float) -> np.ndarray:
        """``T_target_source`` at ``stamp``: maps ``source``-frame points into ``target``.

        Raises
        ------
        TransformUnavailable
            A frame is unknown, the two are not connected, or an edge of the chain has no sample within
            ``tolerance`` of ``stamp`` (the message names the edge and its span).
        """
        target, source = str(target).lstrip("/"), str(source).lstrip("/")
        if target == source:
            return np.eye(4)
        for f in (target, source):
            if f not in self.frames:
                raise TransformUnavailable(f"frame {f!r} is not in the transforms (frames: {sorted(self.frames)})")
        up_t, up_s = self._chain(target), self._chain(source)
        if up_t[-1] != up_s[-1]:
            raise TransformUnavailable(f"frames {target!r} and {source!r} are not connected (roots {up_t[-1]!r} "
                                       f"and {up_s[-1]!r})")
        common = next(f for f in up_s if f in set(up_t))
        T_common_source = np.eye(4)
        for f in up_s[: up_s.index(common)]:
            T_common_source = self._edge(f, stamp) @ T_common_source
        T_common_target = np.eye(4)
        for f in up_t[: up_t.index(common)]:
            T_common_target = self._edge(f, stamp) @ T_common_target
        R, t = T_common_target[:3, :3], T_common_target[:3, 3]
        inv = np.eye(4)
        inv[:3, :3], inv[:3, 3] = R.T, -R.T @ t
        return inv @ T_common_source
