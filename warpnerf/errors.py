"""User-facing errors: the CLI prints their message (no traceback) and exits with status 2."""


class UserError(Exception):
    """A mistake in the user's input (file, field, flag); the message says what and where."""
