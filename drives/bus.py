"""The CAN bus: a python-can bus built from the configured interface name, and a vcan probe.

Source: python-can's interface registry (``can.interfaces.VALID_INTERFACES``) and Linux SocketCAN
(``/sys/class/net/<if>/type`` = 280 is ``ARPHRD_CAN``; ``socket(AF_CAN, SOCK_RAW, CAN_RAW)``
fails with errno 97, ``EAFNOSUPPORT``, on a kernel without CAN).

Units: bitrate in bit/s.

Threading: called at start-up; the returned bus then belongs to one reader: the master's cycle
thread (``recv(timeout=0)`` each period) or, for simulated drives, a ``canopen.Network`` and its
Notifier (python-can >= 4.6 allows one active Notifier per bus).

Not done here: setting the bitrate of a SocketCAN link (that is ``ip link set ... bitrate``, root
only) or creating vcan0; the probe only reports.
"""

from __future__ import annotations

import errno
import socket
from pathlib import Path
from typing import Any

import can
import can.interfaces

from drives.errors import BusUnavailable

#: Where Linux lists network interfaces and their attributes.
SYSFS_NET = Path("/sys/class/net")

#: ARPHRD_CAN, the link type of CAN and vcan interfaces in /sys/class/net/<if>/type.
ARPHRD_CAN = 280

#: Interfaces whose bitrate is not set through python-can: SocketCAN links are configured with
#: ``ip link``, and the software buses have none. Passing one would be silently ignored, so the
#: factory drops it rather than pretend it was applied.
_NO_BITRATE_INTERFACES = frozenset({"virtual", "local", "socketcan", "socketcand", "udp_multicast"})

#: Options the factory adds per interface, keyed by the configured interface name.
_INTERFACE_OPTIONS: dict[str, dict[str, Any]] = {
    # Our own frames do not come back unless asked (receive_own_messages=True: the master then
    # takes the echo of its SYNC for the SYNC's bus time, and ignores its other frames).
    "virtual": {"receive_own_messages": False},
    # Other sockets on the host (listeners, simulated drives) must see our frames.
    "socketcan": {"receive_own_messages": False, "local_loopback": True},
}


def open_bus(interface: str, channel: str, bitrate: int | None = None, **kwargs: Any) -> can.BusABC:
    """Open a python-can bus for any registered interface.

    :param interface: python-can interface name (``virtual``, ``socketcan``, ``pcan``, ...).
    :param channel: the interface's channel (``vcan0``, ``can0``, a virtual channel name).
    :param bitrate: bit/s, passed only to interfaces that set it themselves.
    :param kwargs: further interface options; they override the factory's defaults.
    :raises BusUnavailable: if the name is not a python-can interface or the bus cannot open.
    """
    if interface not in can.interfaces.VALID_INTERFACES:
        known = ", ".join(sorted(can.interfaces.VALID_INTERFACES))
        raise BusUnavailable(interface, channel, f"unknown python-can interface (known: {known})")
    options = dict(_INTERFACE_OPTIONS.get(interface, {}))
    if bitrate is not None and interface not in _NO_BITRATE_INTERFACES:
        options["bitrate"] = bitrate
    options.update(kwargs)
    try:
        return can.Bus(interface=interface, channel=channel, **options)
    except (can.CanError, OSError, ImportError) as exc:
        raise BusUnavailable(interface, channel, f"{type(exc).__name__}: {exc}") from exc


def vcan_status(channel: str = "vcan0") -> tuple[bool, str]:
    """Whether a SocketCAN interface is usable here, and why not when it is not.

    Checks, in order: AF_CAN sockets exist in this Python and kernel, the interface exists and is
    a CAN link (type 280), it is up, and a raw CAN socket binds to it.

    :returns: (usable, reason); the reason names the failed check and how to fix it.
    """
    if not hasattr(socket, "AF_CAN"):
        return False, "this Python has no AF_CAN socket support (not Linux?)"
    try:
        probe = socket.socket(socket.AF_CAN, socket.SOCK_RAW, socket.CAN_RAW)
    except OSError as exc:
        if exc.errno == errno.EAFNOSUPPORT:
            return False, "the kernel has no CAN support (socket(AF_CAN) failed with errno 97)"
        return False, f"socket(AF_CAN, SOCK_RAW, CAN_RAW) failed: {exc}"
    with probe:
        link = SYSFS_NET / channel
        try:
            link_type = int((link / "type").read_text())
        except FileNotFoundError:
            return False, (
                f"no network interface {channel} (modprobe vcan; ip link add dev {channel} "
                f"type vcan; ip link set {channel} up)"
            )
        if link_type != ARPHRD_CAN:
            return False, f"{channel} is not a CAN link (type {link_type}, expected {ARPHRD_CAN})"
        flags = int((link / "flags").read_text(), 16)
        if not flags & 0x1:  # IFF_UP
            return False, f"{channel} is down (ip link set {channel} up)"
        try:
            probe.bind((channel,))
        except OSError as exc:
            return False, f"cannot bind a raw CAN socket to {channel}: {exc}"
    return True, f"{channel} is a usable SocketCAN interface"
