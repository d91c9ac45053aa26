"""What the image-side actions share: the transform method names, the progress callback, the method check.

Each command has one action module (``rectify/actions/<command>.py``, named as its ``rectify/cli`` module):
an options dataclass (whose defaults are the command-line defaults), a function that takes a
:class:`~rectify.actions.workspace.Workspace`, checks every planned output and the report folder
before any work, runs the step and returns a frozen result whose :meth:`summary_lines` are the lines
the command prints.
"""

from __future__ import annotations

from collections.abc import Callable

from rectify.errors import InvalidInputError
from rectify.geometry.transforms import METHODS

#: The transform methods, in the order the commands list them.
METHOD_NAMES: tuple[str, ...] = tuple(METHODS)

Progress = Callable[[int, int], None] | None


def check_method(method: str) -> None:
    if method not in METHODS:
        raise InvalidInputError(f"unknown method {method!r}; expected one of {sorted(METHODS)}")

