"""Errors a user can fix. The CLI prints them as one line (``error: ...``) and exits with status 2."""


class UserError(Exception):
    """A mistake in the user's input: a config key or value, a file, a target.

    The message names the field or file and what was expected, e.g.
    ``"configs/x.yaml: evolution.generations: expected an integer >= 1, got -3"``.
    """
