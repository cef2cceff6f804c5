"""Output files of the commands: one policy for what a run may write (:func:`check_outputs`), and atomic
writes (a temporary file in the target's folder, renamed over it only on success).
"""

from __future__ import annotations

import contextlib
import json
import os
import tempfile
from collections.abc import Iterable, Mapping
from pathlib import Path

from noise_model.reporting import json_ready

__all__ = ["check_outputs", "atomic_output", "write_json_atomic", "json_ready", "new_file_mode"]


def check_outputs(outputs: Mapping[str, object], overwrite: bool = False, inputs: Iterable = (), *,
                  create_folders: bool = False) -> dict[str, Path | None]:
    """Check every output of a run before the run does any work; the one policy of every command.

    Rules, checked for each output in this order:

    1. an output may not be one of the run's ``inputs`` (whatever ``overwrite`` says: a run must not
       destroy what it reads);
    2. an output must be a file path, not an existing folder;
    3. its folder must exist (unless ``create_folders``: then the run makes it, and only a path
       component that is an existing file is refused);
    4. two outputs of one run may not be the same file (the second write would replace the first);
    5. an existing file is refused unless ``overwrite`` (``--overwrite``).

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
        Files the run reads.
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
        overwrite`` (an input), ``is a directory``, ``folder does not exist``, ``different files`` and
        ``exists; pass --overwrite``.
    """
    ins = {Path(p).resolve() for p in inputs if p is not None}
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
        if key in seen:
            raise ValueError(f"{seen[key]} and {what} are the same file {path}; give them different files")
        seen[key] = what
        if p.exists() and not overwrite:
            raise ValueError(f"{what} {path} exists; pass --overwrite to replace it")
        out[what] = p
    return out


@contextlib.contextmanager
def atomic_output(path, suffix: str | None = None):
    """Yield a temporary path next to ``path``; rename it onto ``path`` when the block succeeds.

    On any exception the temporary file is removed and ``path`` is left as it was (absent, or the
    previous complete file), so a crash never leaves a partial output behind. The finished file gets
    the permissions of the file it replaces, or the usual ones of a new file (:func:`new_file_mode`).
    """
    path = Path(path)
    if path.is_dir():
        raise ValueError(f"{path} is a directory, not a file path")
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=suffix or path.suffix or ".tmp", dir=path.parent)
    os.close(fd)
    try:
        yield Path(tmp)
        os.chmod(tmp, new_file_mode(path))
        os.replace(tmp, path)
    except BaseException:
        with contextlib.suppress(FileNotFoundError):
            os.unlink(tmp)
        raise


def new_file_mode(path) -> int:
    """Permissions for a finished output: those of the file it replaces, else 0o666 minus the umask.

    (``tempfile.mkstemp`` creates the temporary file 0o600, which would otherwise stay.)
    """
    try:
        return os.stat(path).st_mode & 0o7777
    except OSError:
        umask = os.umask(0)
        os.umask(umask)
        return 0o666 & ~umask


def write_json_atomic(path, obj) -> None:
    """Write ``obj`` as indented JSON to ``path`` atomically."""
    with atomic_output(path) as tmp:
        tmp.write_text(json.dumps(obj, indent=2) + "\n")
