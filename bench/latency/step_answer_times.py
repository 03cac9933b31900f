"""How long one parallel_env step waits for its answer when the server is loaded: the figure the
default step_timeout_s must stay far above (docs/benchmarks.md, "Step deadline").

Starts one `mll_server --threads=2` on loopback, then `--clients` processes, each stepping its own
`parallel_env(n_landers=3)` with random actions (resetting at each episode's end) for `--seconds`
after a warm-up of a tenth of that, every step timed; prints the quantiles of all steps together
as one JSON line.

    .venv/bin/python bench/latency/step_answer_times.py --clients 8 --seconds 30
"""

from __future__ import annotations

import argparse
import json
import multiprocessing
import time

import numpy as np


def _client(address: str, seconds: float, seed: int, out) -> None:
    import multi_lunar_lander as mll

    env = mll.parallel_env(address=address, n_landers=3)
    rng = np.random.default_rng(seed)
    env.reset(seed=seed)
    times = []
    start = time.monotonic() + seconds / 10
    until = start + seconds
    while time.monotonic() < until:
        began = time.monotonic()
        if env.agents:
            env.step({agent: int(rng.integers(0, 4)) for agent in env.agents})
        else:
            env.reset()
        if began >= start:
            times.append(time.monotonic() - began)
    env.close()
    out.put(times)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--clients", type=int, default=8)
    parser.add_argument("--seconds", type=float, default=30.0)
    args = parser.parse_args()
    import multi_lunar_lander as mll

    with mll.ServerProcess(threads=2) as server:
        out = multiprocessing.Queue()
        clients = [
            multiprocessing.Process(target=_client, args=(server.address, args.seconds, seed, out))
            for seed in range(args.clients)
        ]
        for client in clients:
            client.start()
        times = np.sort(np.concatenate([out.get(timeout=args.seconds * 3 + 60) for _ in clients]))
        for client in clients:
            client.join(timeout=60)

    def ms(q: float) -> float:
        return round(1000 * float(times[max(int(np.ceil(q * times.size)), 1) - 1]), 3)

    print(json.dumps({
        "clients": args.clients, "seconds": args.seconds, "steps": int(times.size),
        "step_ms_p50": ms(0.5), "step_ms_p99": ms(0.99), "step_ms_p999": ms(0.999), "step_ms_max": ms(1.0),
    }))


if __name__ == "__main__":
    main()
