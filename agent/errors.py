"""Errors that reach the user.

``InputError`` is raised for anything the user can fix (a bad file, key, column or option);
the CLI prints its one-line message and exits with status 2. Everything else is a bug and
exits with status 1.
"""


class InputError(Exception):
    """Bad user input. The message names the file, key or column and the problem."""

    def __init__(self, message: str, *, source: str | None = None):
        self.source = source
        super().__init__(f"{source}: {message}" if source else message)
