"""A prober of its own: GET a few URLs every 20 ms from a separate process, so that what it measures is the
service's answer time, not the stalls of a load generator's event loop that shares its process.

Start it with `multiprocessing` (spawn): `Process(target=poll, args=(urls, stop_event, queue))`; it puts
{name: [ms, …]} on the queue once `stop_event` is set (a failed request counts −1).
"""

from __future__ import annotations

import time

import httpx

POLL_EVERY_S = 0.02


def poll(urls: dict[str, str], stop, out) -> None:
    """GET each url in turn every POLL_EVERY_S until stop is set; out gets {name: [ms, ...]} (failures: -1)."""
    times: dict[str, list[float]] = {name: [] for name in urls}
    with httpx.Client(timeout=10) as client:
        while not stop.is_set():
            for name, url in urls.items():
                t0 = time.perf_counter()
                try:
                    ok = client.get(url).status_code in (200, 503)
                except httpx.HTTPError:
                    ok = False
                times[name].append((time.perf_counter() - t0) * 1e3 if ok else -1.0)
            time.sleep(POLL_EVERY_S)
    out.put(times)
