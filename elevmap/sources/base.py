"""What every source of frames has in common: a context manager and an iterator of :class:`Frame`.

Sources never import pyrealsense2 or OpenCV at module level; the modules that need them import them
inside the functions that use them, so everything else works on a machine without them.
"""

from __future__ import annotations

import re
from collections.abc import Iterator

from ..frame import Frame

__all__ = ["FrameSource", "natural_key"]


class FrameSource:
    """Base class of the sources: ``with Source(...) as src: for frame in src: ...``.

    Subclasses implement :meth:`_frames` (a generator of :class:`~elevmap.frame.Frame`) and, when the
    number of frames is known without decoding them, ``__len__``. :meth:`close` releases whatever the
    source holds open; iterating a closed source is an error. Iterating twice starts again from the
    first frame (files) unless a subclass says otherwise (a live camera).
    """

    _closed: bool = False

    def _frames(self) -> Iterator[Frame]:  # pragma: no cover - abstract
        raise NotImplementedError

    def __iter__(self) -> Iterator[Frame]:
        if self._closed:
            raise ValueError(f"{self!r} is closed")
        return self._frames()

    def close(self) -> None:
        """Release the source (files, pipelines). Safe to call more than once."""
        self._closed = True

    @property
    def closed(self) -> bool:
        return self._closed

    def __enter__(self):
        return self

    def __exit__(self, *exc) -> None:
        self.close()


def natural_key(name: str) -> list:
    """Sort key that orders the digit runs of a name by value: ``f2.png`` before ``f10.png``."""
    return [int(t) if t.isdigit() else t for t in re.split(r"(\d+)", name)]

