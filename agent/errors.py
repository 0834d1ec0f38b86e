"""Errors that reach the user, and reading the user's files.

``InputError`` is raised for anything the user can fix (a bad file, key, column or option);
the CLI prints its one-line message and exits with status 2. Everything else is a bug and
exits with status 1.
"""


class InputError(Exception):
    """Bad user input. The message names the file, key or column and the problem."""

    def __init__(self, message: str, *, source: str | None = None):
        self.source = source
        super().__init__(f"{source}: {message}" if source else message)


def read_toml(path, what: str) -> dict:
    """Parse the TOML file ``path``; every failure is an ``InputError`` naming the file and ``what`` it is."""
    import tomllib
    from pathlib import Path

    try:
        return tomllib.loads(Path(path).read_text(encoding="utf-8-sig"))  # a byte-order mark is no error
    except FileNotFoundError:
        raise InputError(f"no such {what} file", source=str(path)) from None
    except (OSError, UnicodeDecodeError) as err:
        raise InputError(f"cannot read {what}: {err}", source=str(path)) from None
    except tomllib.TOMLDecodeError as err:
        raise InputError(f"not valid TOML: {err}", source=str(path)) from None
