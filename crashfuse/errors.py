"""The one error type for bad input: it names the file, the field and what was expected."""

from __future__ import annotations

import os


class InputError(ValueError):
    """Bad user input (file, column, value or argument).

    The CLI prints ``str(err)`` on one line and exits with code 2.

    Parameters
    ----------
    message : str
        What was wrong and what was expected.
    file : str or os.PathLike, optional
        The file or folder the problem is in.
    field : str, optional
        The column, header field, channel or argument concerned.
    """

    def __init__(self, message: str, file: str | os.PathLike | None = None, field: str | None = None):
        self.message = message
        self.file = None if file is None else os.fspath(file)
        self.field = field
        super().__init__(self._render())

    def _render(self) -> str:
        where = ": ".join(p for p in (self.file, self.field and f"field '{self.field}'") if p)
        return f"{where}: {self.message}" if where else self.message

    def at(self, file: str | os.PathLike) -> "InputError":
        """The same error, located in ``file`` (keeps a more specific file already set)."""
        return self if self.file else InputError(self.message, file, self.field)
