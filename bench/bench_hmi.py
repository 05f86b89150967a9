"""Benchmark of the HMI over Modbus TCP: status read latency, pipelined throughput, curve upload.

Prints, for the HMI server and for a reference measured in the same run:

- status read round trip (one FC4 request of the core status, input registers 0-111: identity,
  machine status, axes, cycle statistics) with 1 client back to back, 10 clients at 20 Hz each
  (an HMI and SCADA load) and 10 clients back to back (saturation): p50, p99, max;
- throughput of one connection with 1 and with 8 requests in flight (pipelined);
- the time to upload and commit a 1,000-point curve until the machine has loaded it.

By default the server runs in a process of its own (as the HMI process will) in front of a fake
machine that publishes a snapshot every 4 ms and judges commands each period
(``tests/fake_machine_link.py``). The reference is a bare asyncio server, also in a process of its
own, that answers every frame with a fixed response of the same size: the ratios are the cost of the
HMI's framing, checks and status encoding over the wire and the event loop alone. The clients are
raw sockets on one asyncio loop in this process. ``--port P`` measures a running machine instead
(no reference, no upload unless the machine is DISABLED or STANDBY).

Usage: ``python bench/bench_hmi.py [--port P] [--seconds S]``
"""

from __future__ import annotations

import argparse
import asyncio
import multiprocessing
import struct
import sys
import tempfile
import time
from collections.abc import Callable
from dataclasses import replace
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "tests"))

from runtime.hmi.registers import CORE_END  # noqa: E402

STATUS_REQUEST = struct.pack(">BHH", 4, 0, CORE_END)
STATUS_BYTES = 7 + 2 + 2 * CORE_END


def _frame(tid: int, pdu: bytes) -> bytes:
    return struct.pack(">HHHB", tid, 0, len(pdu) + 1, 1) + pdu


# -- servers, each in a process of its own ----------------------------------------------------


def _serve_hmi(ready: multiprocessing.Queue, stop: multiprocessing.Event) -> None:
    from fake_machine_link import FakeMachine

    from runtime.config import ModbusConfig
    from runtime.hmi.server import HmiServer

    with tempfile.TemporaryDirectory() as tmp:
        machine = FakeMachine(Path(tmp)).start()
        with HmiServer(machine, replace(ModbusConfig(), port=0)) as server:
            ready.put(server.port)
            stop.wait()
        machine.close()


def _serve_reference(ready: multiprocessing.Queue, stop: multiprocessing.Event) -> None:
    """A bare asyncio server: every 12-byte request gets a fixed answer of the core's size."""
    answer_pdu = bytes((4, 2 * CORE_END)) + bytes(2 * CORE_END)

    class Echo(asyncio.Protocol):
        def connection_made(self, transport: asyncio.BaseTransport) -> None:
            self.transport = transport
            self.buffer = bytearray()

        def data_received(self, data: bytes) -> None:
            self.buffer += data
            replies = []
            while len(self.buffer) >= 12:
                tid = int.from_bytes(self.buffer[:2], "big")
                del self.buffer[:12]
                replies.append(_frame(tid, answer_pdu))
            self.transport.write(b"".join(replies))  # type: ignore[attr-defined]

    async def main() -> None:
        loop = asyncio.get_running_loop()
        server = await loop.create_server(Echo, "127.0.0.1", 0)
        ready.put(server.sockets[0].getsockname()[1])
        await loop.run_in_executor(None, stop.wait)
        server.close()

    asyncio.run(main())


class ServerProcess:
    """A server function run in a process of its own; ``port`` once it listens."""

    def __init__(self, target: Callable[[multiprocessing.Queue, multiprocessing.Event], None]):
        context = multiprocessing.get_context("spawn")
        self._ready: multiprocessing.Queue = context.Queue()
        self._stop = context.Event()
        self._process = context.Process(target=target, args=(self._ready, self._stop), daemon=True)
        self._process.start()
        self.port: int = self._ready.get(timeout=30)

    def close(self) -> None:
        self._stop.set()
        self._process.join(10)


# -- clients: raw sockets on one asyncio loop -------------------------------------------------


async def _client(
    port: int, seconds: float, interval_s: float, samples: list[float], start: float
) -> None:
    reader, writer = await asyncio.open_connection("127.0.0.1", port)
    tid = 0
    next_s = start
    while (now := time.perf_counter()) < start + seconds:
        if interval_s and now < next_s:
            await asyncio.sleep(next_s - now)
        tid = (tid + 1) & 0xFFFF
        sent = time.perf_counter()
        writer.write(_frame(tid, STATUS_REQUEST))
        answer = await reader.readexactly(STATUS_BYTES)
        samples.append(time.perf_counter() - sent)
        assert int.from_bytes(answer[:2], "big") == tid
        next_s += interval_s
    writer.close()


def status_round_trip(port: int, clients: int, seconds: float, rate_hz: float = 0.0) -> np.ndarray:
    """Round-trip times (s) of status reads by ``clients`` clients, back to back (rate 0) or
    each at ``rate_hz``."""

    async def run() -> list[float]:
        samples: list[float] = []
        start = time.perf_counter() + 0.05
        interval = 1.0 / rate_hz if rate_hz else 0.0
        await asyncio.gather(
            *(
                _client(port, seconds, interval, samples, start + i * interval / clients)
                for i in range(clients)
            )
        )
        return samples

    return np.array(asyncio.run(run()))


def pipelined_rate(port: int, in_flight: int, seconds: float) -> float:
    """Answered status reads per second on one connection keeping ``in_flight`` requests out."""

    async def run() -> float:
        reader, writer = await asyncio.open_connection("127.0.0.1", port)
        sent = answered = 0
        for _ in range(in_flight):
            sent += 1
            writer.write(_frame(sent & 0xFFFF, STATUS_REQUEST))
        started = time.perf_counter()
        while time.perf_counter() - started < seconds:
            answer = await reader.readexactly(STATUS_BYTES)
            answered += 1
            assert int.from_bytes(answer[:2], "big") == answered & 0xFFFF
            sent += 1
            writer.write(_frame(sent & 0xFFFF, STATUS_REQUEST))
        rate = answered / (time.perf_counter() - started)
        writer.close()
        return rate

    return asyncio.run(run())


def spiral_curve(points: int = 1000) -> tuple[int, np.ndarray, np.ndarray]:
    """A cubic B-spline with ``points`` control points on a rising spiral inside the travel."""
    t = np.linspace(0.0, 12 * np.pi, points)
    control = np.column_stack(
        [100 + 60 * np.cos(t), 80 + 60 * np.sin(t), np.linspace(5.0, 60.0, points)]
    )
    degree = 3
    inner = np.linspace(0.0, 1.0, points - degree + 1)[1:-1]
    knots = np.r_[np.zeros(degree + 1), inner, np.ones(degree + 1)]
    return degree, control, knots


def upload_time(port: int, repeats: int = 3) -> list[float]:
    """Seconds to stage, commit and see loaded a 1,000-point curve."""
    from runtime.hmi.client import HmiClient
    from runtime.hmi.upload import encode_staging

    degree, control, knots = spiral_curve()
    staging = encode_staging(degree, control, knots)
    times = []
    with HmiClient(port=port, timeout_s=30.0) as client:
        for _ in range(repeats):
            started = time.perf_counter()
            client.load_curve(staging)
            times.append(time.perf_counter() - started)
    return times


def _row(label: str, values_ms: np.ndarray, reference_ms: np.ndarray | None) -> str:
    p50, p99, worst = (np.percentile(values_ms, 50), np.percentile(values_ms, 99), values_ms.max())
    ratio = ""
    if reference_ms is not None:
        ratio = f"{p99 / np.percentile(reference_ms, 99):>8.1f}x"
    return f"{label:<34} {len(values_ms):>7} {p50:>8.3f}ms {p99:>8.3f}ms {worst:>8.3f}ms {ratio}"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--port", type=int, help="bench a running machine on this port")
    parser.add_argument("--seconds", type=float, default=3.0, help="per measurement")
    args = parser.parse_args()
    servers: list[ServerProcess] = []
    try:
        if args.port is None:
            hmi = ServerProcess(_serve_hmi)
            reference = ServerProcess(_serve_reference)
            servers += [hmi, reference]
            ports = {"hmi": hmi.port, "reference": reference.port}
        else:
            ports = {"hmi": args.port}
        print(f"HMI benchmark: server on 127.0.0.1:{ports['hmi']}, {args.seconds:g} s each")
        print(
            f"{f'status read (FC4, {CORE_END} registers)':<34} {'n':>7} {'p50':>10} {'p99':>10} "
            f"{'max':>10} {'p99/ref':>9}"
        )
        for label, clients, rate in (
            ("1 client, back to back", 1, 0.0),
            ("10 clients at 20 Hz", 10, 20.0),
            ("10 clients, back to back", 10, 0.0),
        ):
            measured = {
                name: status_round_trip(port, clients, args.seconds, rate) * 1e3
                for name, port in ports.items()
            }
            print(_row(f"  {label}", measured["hmi"], measured.get("reference")))
            if "reference" in measured:
                print(_row("    reference", measured["reference"], None))
        print(f"{'one connection, pipelined':<34} {'req/s':>18} {'reference':>12} {'ratio':>8}")
        for in_flight in (1, 8):
            rates = {
                name: pipelined_rate(port, in_flight, args.seconds) for name, port in ports.items()
            }
            reference_rate = rates.get("reference")
            tail = (
                f"{reference_rate:>12.0f} {rates['hmi'] / reference_rate:>7.2f}x"
                if reference_rate
                else ""
            )
            print(f"  {in_flight} in flight{'':<22} {rates['hmi']:>18.0f} {tail}")
        up = np.array(upload_time(ports["hmi"])) * 1e3
        print(
            f"upload + commit, 1000-point curve: {len(up)} runs, p50 {np.median(up):.1f} ms, "
            f"max {up.max():.1f} ms"
        )
    finally:
        for server in servers:
            server.close()


if __name__ == "__main__":
    main()
