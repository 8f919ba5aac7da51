"""Errors a user can fix. The CLI prints them as one line (``error: ...``) and exits with 2."""


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
