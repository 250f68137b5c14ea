"""The base of the package's typed errors.

Every error the package raises on bad input (a record, a file, a parameter, a model, a backend) derives from
:class:`PiezoValveError` as well as from the built-in class it always was (ValueError, RuntimeError), so a
caller may catch either.  The offline tools end on one with exit code 2 and its message (``tool.run_tool``).
"""
__all__ = ["PiezoValveError"]


class PiezoValveError(Exception):
    """Bad input the package refused, with a message that says what and why."""
