"""Errors a user can fix. The CLI prints them as one line (``error: ...``) and exits with 2."""

from pathlib import Path


class UserError(Exception):
    """A mistake in the user's input: a config key or value, a file, a target.

    The message names the field or file and what was expected, e.g.
    ``"configs/x.yaml: evolution.generations: expected an integer >= 1, got -3"``.
    """


def check_setting(ok: bool, name: str, expected: str, value) -> None:
    """Validation of a settings field in ``__post_init__``: ``ValueError("name: expected ...")``.

    The config loader prefixes the section (``evolution.generations: expected ...``) and turns it
    into a ``UserError``.
    """
    if not ok:
        raise ValueError(f"{name}: expected {expected}, got {value!r}")


def read_user_file(path: Path, what: str) -> str:
    """The UTF-8 text of a file the user named (a config, an MJCF model); ``what`` names its kind.

    Raises `UserError` ``"PATH: WHAT file not found"`` or ``"PATH: unreadable WHAT file (Error)"``.
    """
    if not path.is_file():
        raise UserError(f"{path}: {what} file not found")
    try:
        return path.read_text(encoding="utf-8")
    except (OSError, UnicodeDecodeError) as e:
        raise UserError(f"{path}: unreadable {what} file ({type(e).__name__})") from None
