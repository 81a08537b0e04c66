"""Exceptions shared by every part of volcal."""

from __future__ import annotations


class InputError(ValueError):
    """Bad user input (model file, data table, option).

    The message names the file, and where it applies the row (1-based, as a spreadsheet
    shows it, header = row 1), the column or key, and what was expected.
    """

    def __init__(
        self,
        message: str,
        *,
        source: str | None = None,
        row: int | None = None,
        column: str | None = None,
    ):
        where = []
        if source is not None:
            where.append(str(source))
        if row is not None:
            where.append(f"row {row}")
        if column is not None:
            where.append(f"column '{column}'")
        self.source, self.row, self.column = source, row, column
        super().__init__(f"{', '.join(where)}: {message}" if where else message)


class SolverError(RuntimeError):
    """A numerical solve that did not succeed; ``status`` holds the solver's own word."""

    def __init__(self, message: str, *, status: str | None = None):
        self.status = status
        super().__init__(f"{message} (status: {status})" if status else message)
