"""Exceptions of the drives package.

Hierarchy::

    DriveError                             base: a drive, its bus or its configuration failed
     ├── BusUnavailable                    a CAN interface could not be opened
     ├── BootTimeout (TimeoutError)        a node sent neither boot-up nor heartbeat in time
     ├── ConfigurationFailed               an SDO transfer of the set-up was aborted or timed out
     ├── ConfigurationMismatch             an object read back differs from the value written
     └── ScalingError (ValueError)         a position that has no count value on the drive

Messages start with the node (``node 3: ...``) when one is concerned, then name the object,
the value and the rule, for example ``node 2: 0x6065:00 following error window: wrote 4000,
read back 0``. The fields are attributes, and ``str()`` derives the text from them.
"""

from __future__ import annotations


class DriveError(Exception):
    """Base of every drives error.

    :param node_id: the CANopen node concerned, or None when the error is not about one node.
    :param message: what happened, with the value and the rule it breaks.
    """

    def __init__(self, node_id: int | None, message: str) -> None:
        self.node_id = node_id
        self.message = message
        super().__init__(node_id, message)

    def __str__(self) -> str:
        if self.node_id is None:
            return self.message
        return f"node {self.node_id}: {self.message}"


class BusUnavailable(DriveError):
    """A python-can interface that could not be opened (unknown name, missing device, no driver)."""

    def __init__(self, interface: str, channel: str, reason: str) -> None:
        self.interface = interface
        self.channel = channel
        self.reason = reason
        super().__init__(None, f"CAN bus {interface}:{channel}: {reason}")


class BootTimeout(DriveError, TimeoutError):
    """A node that sent neither a boot-up message nor a heartbeat within the boot timeout."""

    def __init__(self, node_id: int, timeout_s: float, also_silent: tuple[int, ...] = ()) -> None:
        self.timeout_s = timeout_s
        self.also_silent = also_silent
        message = f"no boot-up or heartbeat within {timeout_s:g} s"
        if also_silent:
            message += f" (also silent: node {', node '.join(map(str, also_silent))})"
        super().__init__(node_id, message)


class ConfigurationFailed(DriveError):
    """An SDO transfer of the set-up that the drive aborted or did not answer.

    :param index: object index, e.g. ``0x6060``.
    :param subindex: object sub-index.
    :param name: the object's name, e.g. ``"modes of operation"``.
    :param cause: the SDO error text (abort code and meaning, or the timeout).
    """

    def __init__(self, node_id: int, index: int, subindex: int, name: str, cause: str) -> None:
        self.index = index
        self.subindex = subindex
        self.name = name
        self.cause = cause
        super().__init__(node_id, f"0x{index:04X}:{subindex:02X} {name}: {cause}")


class ConfigurationMismatch(DriveError):
    """An object whose value read back after the set-up differs from the value written."""

    def __init__(
        self, node_id: int, index: int, subindex: int, name: str, written: int, read: int
    ) -> None:
        self.index = index
        self.subindex = subindex
        self.name = name
        self.written = written
        self.read = read
        super().__init__(
            node_id,
            f"0x{index:04X}:{subindex:02X} {name}: wrote {written}, read back {read}",
        )


class ScalingError(DriveError, ValueError):
    """A position in millimetres whose count value does not fit the drive's INTEGER32 target."""

    def __init__(self, position_mm: float, counts: float) -> None:
        self.position_mm = position_mm
        self.counts = counts
        super().__init__(
            None,
            f"position {position_mm!r} mm = {counts!r} counts: must be finite and within "
            "INTEGER32 (-2147483648..2147483647)",
        )
