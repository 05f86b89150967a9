"""Errors of the runtime package: one family, each message naming what is wrong and where."""

from __future__ import annotations

from typing import Any


class RuntimeFault(Exception):
    """Base of every runtime error."""


class ConfigError(RuntimeFault, ValueError):
    """A machine description that does not validate.

    ``key_path`` names the offending key (``axes[1].node_id``), ``value`` what was found and
    ``expected`` the rule it breaks.
    """

    def __init__(self, key_path: str, value: Any, expected: str) -> None:
        self.key_path = key_path
        self.value = value
        self.expected = expected
        super().__init__(f"config: {key_path} = {value!r}: expected {expected}")


class CommandRejected(RuntimeFault):
    """A machine command that is not allowed now; nothing was changed.

    ``result`` is the :class:`runtime.commands.CommandResult` the HMI sees.
    """

    def __init__(self, result: Any, reason: str) -> None:
        self.result = result
        self.reason = reason
        super().__init__(reason)
