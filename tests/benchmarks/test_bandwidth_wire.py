"""The bandwidth benchmark's wire count (benchmarks.bandwidth.CountingProxy): every byte a server sends through it,
counted once, in the second it arrived; what the client sends is counted apart."""

from __future__ import annotations

import asyncio
import time

from benchmarks.bandwidth import CountingProxy, per_second


def test_the_proxy_counts_every_byte_the_server_sends():
    async def main() -> tuple[CountingProxy, bytes, bytes]:
        async def serve(reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
            asked = await reader.readexactly(5)
            for size in (1, 300, 70_000):  # a few writes, one larger than a read
                writer.write(bytes([size % 251]) * size)
                await writer.drain()
            writer.write(asked)
            await writer.drain()
            writer.close()

        server = await asyncio.start_server(serve, "127.0.0.1", 0)
        proxy = await CountingProxy(server.sockets[0].getsockname()[1]).start()
        reader, writer = await asyncio.open_connection("127.0.0.1", proxy.port)
        writer.write(b"hello")
        await writer.drain()
        got = await reader.read()  # to the end: the server closed
        writer.close()
        await proxy.close()
        server.close()
        return proxy, got, b"hello"

    proxy, got, sent = asyncio.run(main())
    assert got[-5:] == sent and len(got) == 1 + 300 + 70_000 + 5
    assert proxy.down == len(got) and proxy.up == len(sent)
    assert sum(n for _, n in proxy.arrivals) == proxy.down


def test_per_second_puts_each_arrival_in_its_second_of_stream_time():
    start = time.monotonic()
    arrivals = [(start - 1.0, 7), (start + 0.2, 10), (start + 1.5, 20), (start + 1.9, 1), (start + 99.0, 5)]
    assert per_second(arrivals, start, 3, 1.0) == [17, 21, 5]  # before the start → first; after the end → last
    assert per_second(arrivals, start, 4, 2.0) == [17, 0, 0, 26]  # the robot at 2× real time: stream seconds
