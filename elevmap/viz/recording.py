"""rerun recordings written atomically: :func:`open_recording` and :class:`AtomicRecording`.

:func:`open_recording` writes the ``.rrd`` to a hidden temporary file in the destination folder and
renames it over the destination only when the recording is finalised without error, so a failed or
interrupted run never leaves a partial file at the destination and never damages a file that was
already there (a *successful* run does replace it).
"""

from __future__ import annotations

import os
import warnings

import rerun as rr
import rerun.blueprint as rrb

from ..fileio import check_interrupted, new_file_mode, new_temp_file, release_temp

__all__ = ["AtomicRecording", "open_recording"]


class AtomicRecording:
    """A rerun recording saved atomically to ``path`` (and/or streamed to a spawned viewer).

    Use it as a context manager; ``with`` yields the :class:`rerun.RecordingStream` to log to::

        with open_recording("demo.rrd", "elevmap") as rec:
            log_points(rec, "world/points", points_world)

    On a normal exit the stream is flushed, the file sink closed (footer written), the temporary
    file fsync'ed and renamed over ``path`` with :func:`os.replace`. On an exception (including
    ``KeyboardInterrupt``, and SIGTERM/SIGHUP under :func:`elevmap.fileio.handle_signals`) the temporary
    file is deleted and ``path`` is left untouched. Without ``with``, call :meth:`finalise` or
    :meth:`abort` yourself. A process killed outright (SIGKILL, power loss) can leave a hidden
    ``.<name>.elevmap-tmp-<pid>-<random>.part`` file, never a partial ``path``; the next run writing
    ``path`` removes it (:func:`elevmap.fileio.remove_leftovers`).

    With ``spawn=True`` the ``rerun`` viewer executable must be on PATH (it is in the venv's
    ``bin``). If the viewer is unreachable (no display, closed early) :meth:`finalise` warns
    (``RuntimeWarning``) and still writes the file.

    Attributes
    ----------
    recording : rerun.RecordingStream
        The stream to log to.
    path : str or None
        Absolute destination of the ``.rrd`` file (None: viewer only).
    tmp_path : str or None
        The temporary file being written, in the same folder as ``path``; None once closed.
    """

    def __init__(self, path, application_id: str, recording_id: str | None = None, spawn: bool = False,
                 blueprint: rrb.Blueprint | None = None):
        if path is None and not spawn:
            raise ValueError("open_recording needs a path, spawn=True, or both")
        self.path = None if path is None else os.path.abspath(os.fspath(path))
        self.tmp_path = None
        self._closed = False
        self._viewer = bool(spawn)
        if self.path is not None:
            if os.path.isdir(self.path):
                raise IsADirectoryError(f"{self.path} is a directory, not an .rrd file path")
            self.tmp_path = str(new_temp_file(self.path, ".part"))
        try:
            self.recording = rr.RecordingStream(application_id, recording_id=recording_id)
            sinks = []
            if self.tmp_path is not None:
                sinks.append(rr.FileSink(self.tmp_path))
            if spawn:
                self.recording.spawn(connect=False)
                sinks.append(rr.GrpcSink())
            self.recording.set_sinks(*sinks, default_blueprint=blueprint)
        except BaseException:
            self._remove_tmp()
            raise

    # -- context manager ----------------------------------------------------------------------
    def __enter__(self) -> rr.RecordingStream:
        return self.recording

    def __exit__(self, exc_type, exc, tb) -> bool:
        if exc_type is None:
            self.finalise()
        else:
            self.abort()
        return False

    # -- closing ------------------------------------------------------------------------------
    def finalise(self, timeout_sec: float = 120.0) -> str | None:
        """Flush, close the sinks and atomically move the file into place.

        Returns
        -------
        str or None
            The destination path, or None when recording to a viewer only.
        """
        if self._closed:
            return self.path
        try:
            try:
                self.recording.flush(timeout_sec=timeout_sec)
            except RuntimeError as exc:
                # A viewer that died or never started must not cost the user the file: the gRPC sink
                # fails the flush, the file sink is unaffected and is closed by disconnect() below.
                if not (self._viewer and "grpc" in str(exc).lower()):
                    raise OSError(f"{self.path}: the recording could not be written ({exc}); is its disk "
                                  "full?") from None
                warnings.warn(f"rerun viewer unreachable ({exc}); the recording file is still written",
                              RuntimeWarning, stacklevel=2)
            self.recording.disconnect()          # closes the file sink and writes the footer
            if self.tmp_path is not None:
                check_interrupted()
                with open(self.tmp_path, "rb") as fh:
                    os.fsync(fh.fileno())
                os.chmod(self.tmp_path, new_file_mode(self.path))
                os.replace(self.tmp_path, self.path)
                release_temp(self.tmp_path)
                self.tmp_path = None
                _fsync_dir(os.path.dirname(self.path))
        except BaseException:
            self.abort()
            raise
        self._closed = True
        return self.path

    close = finalise

    def abort(self) -> None:
        """Close the stream and delete the temporary file; ``path`` is not touched."""
        if self._closed:
            return
        self._closed = True
        try:
            self.recording.disconnect()
        except Exception:  # noqa: BLE001 - cleaning up after a failure; the original error matters
            pass
        finally:
            self._remove_tmp()

    def _remove_tmp(self) -> None:
        if self.tmp_path is not None:
            release_temp(self.tmp_path, remove=True)
            self.tmp_path = None


def _fsync_dir(directory: str) -> None:
    try:
        fd = os.open(directory, os.O_RDONLY)
    except OSError:
        return
    try:
        os.fsync(fd)
    except OSError:
        pass
    finally:
        os.close(fd)


def open_recording(path, application_id: str, recording_id: str | None = None, spawn: bool = False,
                   blueprint: rrb.Blueprint | None = None) -> AtomicRecording:
    """Open a recording that is written atomically to ``path`` and/or streamed to a new viewer.

    Parameters
    ----------
    path : str or os.PathLike or None
        Destination ``.rrd`` file. Data goes to a hidden temporary file in the same folder
        (``.<name>.elevmap-tmp-<pid>-<random>.part``) until :meth:`AtomicRecording.finalise`. None: no file.
    application_id : str
        rerun application id (the viewer keys blueprints on it).
    recording_id : str, optional
        rerun recording id; random when None.
    spawn : bool
        Also start a rerun viewer and stream to it.
    blueprint : rerun.blueprint.Blueprint, optional
        Default layout stored with the recording (see :func:`default_blueprint`).

    Returns
    -------
    AtomicRecording
        A context manager; ``with open_recording(...) as rec`` gives the ``rr.RecordingStream``.

    Raises
    ------
    ValueError
        If neither ``path`` nor ``spawn`` is given.
    FileNotFoundError
        If the destination folder does not exist (raised before anything is logged).
    """
    return AtomicRecording(path, application_id, recording_id=recording_id, spawn=spawn, blueprint=blueprint)
