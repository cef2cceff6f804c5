"""Command-line option parsing shared by the subcommands (lists of names such as ``--mappers``)."""

from __future__ import annotations

__all__ = ["check_names"]


def check_names(spec, option: str, allowed=None, what: str = "name") -> list[str]:
    """A list of distinct names from a comma-separated string or a sequence (a command-line option).

    Parameters
    ----------
    spec : str or sequence of str
    option : str
        The option's name for messages, e.g. ``"--mappers"``.
    allowed : sequence of str, optional
        The names known; others are an error naming them.
    what : str
        What one name is, for messages ("mapper", "effect", "capture").

    Raises
    ------
    ValueError
        An empty entry, an unknown name, a name given twice.
    """
    if isinstance(spec, str):
        names = [s.strip() for s in spec.split(",")]
    else:
        try:
            names = [str(s).strip() for s in spec]
        except TypeError:
            raise ValueError(f"{option} must be comma-separated {what}s or a list of them, got {spec!r}") from None
    if not names or any(not n for n in names):
        hint = f" of {', '.join(allowed)}" if allowed is not None else ""
        raise ValueError(f"{option} {spec!r}: give comma-separated {what}s{hint}")
    if allowed is not None:
        for n in names:
            if n not in allowed:
                raise ValueError(f"unknown {what} {n!r}; {what}s: {', '.join(allowed)}")
    if len(set(names)) != len(names):
        raise ValueError(f"{option} {spec!r} names a {what} twice")
    return names
