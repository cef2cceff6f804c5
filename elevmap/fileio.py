"""Output files of the commands: the one output policy.

* :func:`check_outputs`, before a run does any work: outputs are not inputs, not folders, not each other,
  their folders exist and are writable, existing files are replaced only with ``--overwrite``; it also
  removes what a killed earlier run left behind (:func:`remove_leftovers`).
* Files are written to a temporary name in the target's folder and renamed over the target only on
  success (:func:`atomic_output`, :func:`write_json_atomic`, the rerun recordings of
  :mod:`elevmap.viz.recording` through :func:`new_temp_file`); a folder output (a capture set) is built in a
  temporary folder and swapped in once complete (:func:`atomic_folder`), the previous one kept until then.
* Every temporary is named ``.<name>.elevmap-tmp-<pid>-<random><suffix>`` (:data:`TEMP_TAG`): a run that
  was killed outright (SIGKILL, power loss) can leave one, and the next run writing the same output
  recognises it by that name and removes it once its process no longer exists.
* :func:`handle_signals` turns SIGINT, SIGTERM and SIGHUP into :class:`Interrupted` (a
  ``KeyboardInterrupt``), so that the clean-up of every temporary runs on ``timeout``, ``docker stop`` or a
  closed terminal as it does on Ctrl-C; :func:`remove_temporaries` removes any still registered. A signal
  whose exception was swallowed (it landed in a C callback) is raised again before any output is renamed
  into place (:func:`check_interrupted`).
* Finished outputs get the permissions of the file they replace, or 0o666 (folders 0o777) minus the
  umask (:func:`new_file_mode`).
"""

from __future__ import annotations

import contextlib
import ctypes
import errno
import json
import os
import re
import secrets
import shutil
import signal
import sys
import threading
from collections.abc import Iterable, Mapping
from pathlib import Path

from noise_model.reporting import json_ready

__all__ = ["check_outputs", "atomic_output", "atomic_folder", "write_json_atomic", "json_ready", "new_file_mode",
           "new_temp_file", "release_temp", "remove_leftovers", "remove_temporaries", "handle_signals", "Interrupted",
           "check_interrupted",
           "TEMP_TAG", "input_files", "check_folder_output"]

#: Marks the name of every temporary file or folder an output is written to.
TEMP_TAG = "elevmap-tmp"

_TEMP_RE = re.compile(rf"^\.(?P<name>.+)\.{TEMP_TAG}-(?P<pid>\d+)-[0-9a-f]+(?:\..*)?$")

_live: set[Path] = set()           # temporaries of this process not yet renamed or removed
_live_lock = threading.Lock()


class Interrupted(KeyboardInterrupt):
    """SIGINT, SIGTERM or SIGHUP received under :func:`handle_signals`; ``signum`` says which."""

    def __init__(self, signum: int):
        super().__init__(signal.Signals(signum).name)
        self.signum = int(signum)


# ------------------------------------------------------------------------------------------------
# temporaries


def _temp_name(path: Path, suffix: str = "") -> Path:
    return path.parent / f".{path.name}.{TEMP_TAG}-{os.getpid()}-{secrets.token_hex(4)}{suffix}"


def _register(p: Path) -> None:
    with _live_lock:
        _live.add(p)


def _unregister(p: Path) -> None:
    with _live_lock:
        _live.discard(p)


def _remove_path(p: Path) -> None:
    if p.is_dir() and not p.is_symlink():
        shutil.rmtree(p, ignore_errors=True)
    else:
        with contextlib.suppress(FileNotFoundError):
            p.unlink()


def new_temp_file(path, suffix: str = "") -> Path:
    """Create an empty temporary file (mode 0o600) beside ``path``, registered for :func:`remove_temporaries`.

    The name is ``.<name>.elevmap-tmp-<pid>-<random><suffix>`` so that a leftover of a killed run is
    recognised (:func:`remove_leftovers`). The caller renames it over ``path`` (then calls
    :func:`release_temp`) or removes it.
    """
    path = Path(path)
    while True:
        tmp = _temp_name(path, suffix)
        try:
            fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o600)
        except FileExistsError:
            continue
        os.close(fd)
        _register(tmp)
        return tmp


def release_temp(tmp, remove: bool = False) -> None:
    """Forget a temporary of :func:`new_temp_file` (renamed into place), or with ``remove`` delete it."""
    tmp = Path(tmp)
    if remove:
        _remove_path(tmp)
    _unregister(tmp)


def remove_temporaries() -> list[Path]:
    """Remove every temporary this process still holds (after an interruption); returns them."""
    with _live_lock:
        live = list(_live)
        _live.clear()
    for p in live:
        _remove_path(p)
    return live


def _pid_alive(pid: int) -> bool:
    if pid == os.getpid():
        return True
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    return True


def remove_leftovers(path) -> list[Path]:
    """Remove the temporaries of ``path`` left by runs that no longer exist (killed outright); returns them.

    Temporaries of a process still running (another run writing the same output) are left alone. A
    previous folder that a killed run had moved aside (``.old``) while ``path`` is missing is moved back.
    """
    path = Path(path)
    folder = path.parent
    removed: list[Path] = []
    try:
        entries = list(os.scandir(folder))
    except OSError:
        return removed
    for e in entries:
        m = _TEMP_RE.match(e.name)
        if m is None or m["name"] != path.name or _pid_alive(int(m["pid"])):
            continue
        if e.name.endswith(_OLD) and e.is_dir() and not os.path.lexists(path):
            os.rename(e.path, path)
            continue
        _remove_path(Path(e.path))
        removed.append(Path(e.path))
    return removed


# ------------------------------------------------------------------------------------------------
# the checks before a run


def input_files(inputs: Iterable) -> set[Path]:
    """The files a run reads, resolved: each input, and for an input folder the files in it that a source
    reads (a capture set: ``captures.json`` and its depth files; another folder: the files directly in it)."""
    out: set[Path] = set()
    for p in inputs:
        if p is None:
            continue
        p = Path(p)
        out.add(p.resolve())
        if not p.is_dir():
            continue
        index = p / "captures.json"
        if index.is_file():
            out.add(index.resolve())
            with contextlib.suppress(OSError, ValueError, RecursionError, TypeError, AttributeError):
                for cap in json.loads(index.read_text()).get("captures", []):
                    if isinstance(cap, dict) and isinstance(cap.get("depth"), str):
                        out.add((p / cap["depth"]).resolve())
        else:
            with contextlib.suppress(OSError):
                out.update(e.resolve() for e in p.iterdir() if e.is_file())
    return out


def _check_writable(folder: Path, what: str, path) -> None:
    """Create and remove a probe file in ``folder``: the one test that sees permissions, read-only mounts
    and immutable folders alike (``os.access`` does not for root)."""
    try:
        probe = new_temp_file(folder / "probe")
    except OSError as exc:
        raise ValueError(f"{what} {path}: cannot write in its folder {folder} ({exc.strerror or exc})") from None
    release_temp(probe, remove=True)


def check_outputs(outputs: Mapping[str, object], overwrite: bool = False, inputs: Iterable = (), *,
                  create_folders: bool = False) -> dict[str, Path | None]:
    """Check every output of a run before the run does any work; the one policy of every command.

    Rules, checked for each output in this order:

    1. an output may not be one of the run's ``inputs`` (whatever ``overwrite`` says: a run must not
       destroy what it reads); an input folder stands for the files in it a source reads
       (:func:`input_files`);
    2. an output must be a file path, not an existing folder;
    3. its folder must exist (unless ``create_folders``: then the run makes it, and only a path
       component that is an existing file is refused) and be writable;
    4. two outputs of one run may not be the same file (the second write would replace the first);
    5. an existing file is refused unless ``overwrite`` (``--overwrite``).

    Before the rules, temporaries of the outputs left by killed runs are removed (:func:`remove_leftovers`).
    Checking first means a refused run leaves every file as it was and costs nothing; the writes
    themselves are atomic (:func:`atomic_output`), so a run that fails later leaves no partial file.

    Parameters
    ----------
    outputs : mapping of str to path or None
        What each output is, as the user knows it (an option such as ``"--json"``, or a parameter name),
        to its path; None entries (outputs not asked for) are skipped.
    overwrite : bool
        Replace existing files.
    inputs : iterable of path
        Files (or folders) the run reads.
    create_folders : bool
        The run creates missing folders of its outputs.

    Returns
    -------
    dict of str to Path or None
        The outputs as :class:`pathlib.Path` (None kept), in the order given.

    Raises
    ------
    ValueError
        The first rule broken, naming the output and its path; the messages say ``refusing to
        overwrite`` (an input), ``is a directory``, ``folder does not exist``, ``cannot write``,
        ``different files`` and ``exists; pass --overwrite``.
    """
    for path in outputs.values():
        if path is not None:
            remove_leftovers(path)
    ins = input_files(inputs)
    seen: dict[Path, str] = {}
    out: dict[str, Path | None] = {}
    for what, path in outputs.items():
        if path is None:
            out[what] = None
            continue
        p = Path(path)
        key = p.resolve()
        if key in ins:
            raise ValueError(f"{what} {path} is an input of this run; refusing to overwrite it")
        if p.is_dir():
            raise ValueError(f"{what} {path} is a directory, not a file path")
        parent = key.parent
        if not create_folders and not parent.is_dir():
            raise ValueError(f"{what} {path}: its folder does not exist")
        blocking = next((a for a in [parent, *parent.parents] if a.exists()), None)
        if blocking is not None and not blocking.is_dir():
            raise ValueError(f"{what} {path}: {blocking} is a file, not a folder")
        if blocking is not None:
            _check_writable(blocking, what, path)
        if key in seen:
            raise ValueError(f"{seen[key]} and {what} are the same file {path}; give them different files")
        seen[key] = what
        if p.exists() and not overwrite:
            raise ValueError(f"{what} {path} exists; pass --overwrite to replace it")
        out[what] = p
    return out


def check_folder_output(what: str, folder, overwrite: bool, own_files, inputs: Iterable = (), *,
                        kind: str = "an output") -> Path:
    """Check a folder output (built whole and swapped in by :func:`atomic_folder`) before any work.

    The folder may be new, empty, or (with ``overwrite``) an earlier output of the same kind holding only
    ``own_files(folder)`` (a callable returning the names that belong to it, or None when the folder is
    not such an output; ``kind`` names it in messages); a folder holding anything else is refused, since
    replacing it would delete that.
    Its parent must exist or be creatable and be writable; leftovers of killed runs are removed.

    Returns
    -------
    Path
        The folder, absolute (a folder swapped in is a new directory: a relative name such as "." would
        still mean the old one).
    """
    folder = Path(folder)
    remove_leftovers(os.path.abspath(folder))
    ins = input_files(inputs)
    if folder.resolve() in ins or any(folder.resolve() in q.parents for q in ins):
        raise ValueError(f"{what} {folder} holds an input of this run; refusing to replace it")
    if folder.exists() and not folder.is_dir():
        raise ValueError(f"{what} {folder} is a file, not a folder")
    parent = folder.resolve().parent
    blocking = next((a for a in [parent, *parent.parents] if a.exists()), None)
    if blocking is not None and not blocking.is_dir():
        raise ValueError(f"{what} {folder}: {blocking} is a file, not a folder")
    if blocking is not None:
        _check_writable(blocking, what, folder)
    if folder.is_dir():
        present = sorted(e.name for e in folder.iterdir())
        if present:
            own = own_files(folder)
            if own is None:
                raise ValueError(f"{what} {folder} exists and holds other files ({', '.join(present[:5])}"
                                 f"{', ...' if len(present) > 5 else ''}); choose a new or empty folder")
            if not overwrite:
                raise ValueError(f"{what} {folder} already holds {kind}; pass --overwrite to replace it")
            foreign = [n for n in present if n not in set(own)]
            if foreign:
                raise ValueError(f"{what} {folder} also holds files that are not part of it "
                                 f"({', '.join(foreign[:5])}{', ...' if len(foreign) > 5 else ''}); replacing "
                                 "the folder would delete them: move them out first")
    return Path(os.path.abspath(folder))


# ------------------------------------------------------------------------------------------------
# atomic writes


@contextlib.contextmanager
def atomic_output(path, suffix: str | None = None):
    """Yield a temporary path next to ``path``; rename it onto ``path`` when the block succeeds.

    On any exception (an interruption included) the temporary file is removed and ``path`` is left as it
    was (absent, or the previous complete file), so a crash never leaves a partial output behind. The
    finished file is flushed to disk before the rename and gets the permissions of the file it replaces,
    or the usual ones of a new file (:func:`new_file_mode`).
    """
    path = Path(path)
    if path.is_dir():
        raise ValueError(f"{path} is a directory, not a file path")
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = new_temp_file(path, suffix or path.suffix or ".tmp")
    try:
        yield tmp
        check_interrupted()
        with open(tmp, "rb+") as fh:
            os.fsync(fh.fileno())
        os.chmod(tmp, new_file_mode(path))
        os.replace(tmp, path)
        release_temp(tmp)
    except OSError as exc:
        release_temp(tmp, remove=True)
        if exc.filename is None and exc.errno is not None:    # a failed write (a full disk) names no file
            raise OSError(exc.errno, exc.strerror, str(path)) from None
        raise
    except BaseException:
        release_temp(tmp, remove=True)
        raise


_RENAME_EXCHANGE = 2
_OLD = ".old"                       # the previous folder, moved aside for the moment of a two-rename swap
_AT_FDCWD = -100


def _exchange(a: Path, b: Path) -> bool:
    """Swap two paths atomically (Linux ``renameat2(RENAME_EXCHANGE)``); False where unsupported."""
    try:
        libc = ctypes.CDLL(None, use_errno=True)
        fn = libc.renameat2
    except (OSError, AttributeError):
        return False
    fn.argtypes = [ctypes.c_int, ctypes.c_char_p, ctypes.c_int, ctypes.c_char_p, ctypes.c_uint]
    if fn(_AT_FDCWD, os.fsencode(a), _AT_FDCWD, os.fsencode(b), _RENAME_EXCHANGE) == 0:
        return True
    err = ctypes.get_errno()
    if err in (errno.ENOSYS, errno.EINVAL, errno.EOPNOTSUPP):
        return False
    raise OSError(err, os.strerror(err), str(b))


@contextlib.contextmanager
def atomic_folder(path):
    """Yield a new temporary folder beside ``path``; when the block succeeds it replaces ``path`` whole.

    An existing ``path`` stays as it was until the new folder is complete; the two are then swapped in one
    step (``renameat2(RENAME_EXCHANGE)``; where the system lacks it, two renames) and the previous folder
    is removed. On any exception the temporary folder is removed and ``path`` is untouched.
    :func:`check_folder_output` checks the destination first.
    """
    path = Path(os.path.abspath(path))          # "." names a folder that can be swapped too
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = _temp_name(path)
    os.mkdir(tmp, 0o700)
    _register(tmp)
    try:
        yield tmp
        check_interrupted()
        os.chmod(tmp, new_file_mode(path, folder=True))
        with _signals_blocked():                    # no interruption between the renames of a swap
            if not path.exists():
                os.rename(tmp, path)
                _unregister(tmp)
                return
            if not _exchange(tmp, path):
                old = _temp_name(path, _OLD)
                os.rename(path, old)
                try:
                    os.rename(tmp, path)
                except BaseException:
                    os.rename(old, path)            # the previous folder back in place
                    raise
                _unregister(tmp)
                tmp = old
                _register(tmp)
        # tmp now holds the previous folder
        _fsync_dir(path.parent)
        release_temp(tmp, remove=True)
    except BaseException:
        release_temp(tmp, remove=True)
        raise


@contextlib.contextmanager
def _signals_blocked():
    """Hold SIGINT, SIGTERM and SIGHUP back for the block (they are delivered after it)."""
    sigs = {signal.SIGINT, signal.SIGTERM, signal.SIGHUP}
    previous = signal.pthread_sigmask(signal.SIG_BLOCK, sigs)
    try:
        yield
    finally:
        signal.pthread_sigmask(signal.SIG_SETMASK, previous)


def _fsync_dir(directory) -> None:
    with contextlib.suppress(OSError):
        fd = os.open(directory, os.O_RDONLY)
        try:
            os.fsync(fd)
        finally:
            os.close(fd)


def new_file_mode(path, folder: bool = False) -> int:
    """Permissions for a finished output: those of the file it replaces, else 0o666 (a folder 0o777) minus
    the umask.

    (Temporaries are created 0o600 / 0o700, which would otherwise stay.)
    """
    try:
        return os.stat(path).st_mode & 0o7777
    except OSError:
        umask = os.umask(0)
        os.umask(umask)
        return (0o777 if folder else 0o666) & ~umask


def write_json_atomic(path, obj) -> None:
    """Write ``obj`` as indented strict JSON (NaN and infinities as null, :func:`json_ready`) to ``path``
    atomically."""
    text = json.dumps(json_ready(obj), indent=2, allow_nan=False) + "\n"
    with atomic_output(path) as tmp:
        tmp.write_text(text)


# ------------------------------------------------------------------------------------------------
# signals

#: The signal :func:`handle_signals` last turned into :class:`Interrupted`, None when there was none. An
#: exception raised by a signal handler is lost when the signal lands while C code runs a Python callback
#: (numba's compiler caching a kernel calls back through ctypes: Python prints "Exception ignored" and goes
#: on), so the outputs check it before they commit (:func:`check_interrupted`).
_pending_signal = None


def check_interrupted() -> None:
    """Raise :class:`Interrupted` for a signal whose exception was lost (see :data:`_pending_signal`);
    called before an output is renamed into place and at the end of :func:`handle_signals`."""
    if _pending_signal is not None:
        raise Interrupted(_pending_signal)



@contextlib.contextmanager
def handle_signals():
    """Within the block SIGINT, SIGTERM and SIGHUP raise :class:`Interrupted` in the main thread, so that every ``finally`` and ``except`` that removes a temporary runs; on the
    way out the temporaries still registered are removed and the previous handlers restored.

    Outside the main thread it does nothing (Python delivers signals to the main thread only).
    """
    global _pending_signal
    if threading.current_thread() is not threading.main_thread():
        yield
        return

    def raise_interrupted(signum, frame):
        global _pending_signal
        _pending_signal = signum                    # kept: the exception may be swallowed (below)
        raise Interrupted(signum)

    def quiet_unraisable(unraisable):
        # swallowed by C code: recorded, raised again later. And once a signal has arrived, an object whose
        # construction it cut short may fail in its finalizer (rerun's RecordingStream without its native
        # stream), even after this block has been left: the run is being torn down, that is not the user's
        # concern, and its traceback must not bury the one-line message.
        if isinstance(unraisable.exc_value, Interrupted) or _pending_signal is not None:
            return
        previous_hook(unraisable)

    _pending_signal = None
    previous = {}
    for sig in (signal.SIGINT, signal.SIGTERM, signal.SIGHUP):
        previous[sig] = signal.signal(sig, raise_interrupted)
    previous_hook = sys.unraisablehook
    sys.unraisablehook = quiet_unraisable
    try:
        yield
        check_interrupted()
    except KeyboardInterrupt:
        for sig in (signal.SIGINT, signal.SIGTERM, signal.SIGHUP):   # a second signal may not stop the clean-up
            signal.signal(sig, signal.SIG_IGN)
        remove_temporaries()
        raise
    finally:
        if _pending_signal is None:             # else kept: finalizers run as the exception is dropped
            sys.unraisablehook = previous_hook
        for sig, handler in previous.items():
            if handler is not None:
                signal.signal(sig, handler)
