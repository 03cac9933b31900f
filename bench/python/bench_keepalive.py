#!/usr/bin/env python3
"""What a lease renewal costs: p50 of one KeepAlive call carrying 1, 100 and 1,000 env names
(what the clients send per connection every third of --idle_timeout_s), against a floor measured
in the same run: p50 of GetEnv of one env, the cheapest unary call that touches an env. Python
gRPC stub, loopback, 200 calls per measurement, rounds alternating ours and the floor.

    .venv/bin/python bench/python/bench_keepalive.py --server build/server/service/mll_server
"""

from __future__ import annotations

import argparse
import statistics
import time

import grpc

import multi_lunar_lander as mll
from multi_lunar_lander._stubs import pb, pb_grpc

CALLS = 200
ROUNDS = 3
COUNTS = (1, 100, 1000)


def p50_us(call, request) -> float:
    samples = []
    for _ in range(CALLS):
        start = time.perf_counter_ns()
        call(request)
        samples.append(time.perf_counter_ns() - start)
    return statistics.median(samples) / 1000


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--server", default=None, help="mll_server binary (default: as the tests find it)")
    args = parser.parse_args()
    with mll.ServerProcess(args.server, threads=2, max_envs=max(COUNTS)) as server:
        with grpc.insecure_channel(server.address) as channel:
            stub = pb_grpc.MultiLunarLanderStub(channel)
            config = pb.EnvConfig(n_landers=1)
            names = [stub.CreateEnv(pb.CreateEnvRequest(config=config)).name for _ in range(max(COUNTS))]
            floor = pb.GetEnvRequest(name=names[0])
            rows = {count: ([], []) for count in COUNTS}
            for _ in range(ROUNDS):
                for count in COUNTS:
                    rows[count][0].append(p50_us(stub.KeepAlive, pb.KeepAliveRequest(names=names[:count])))
                    rows[count][1].append(p50_us(stub.GetEnv, floor))
    print("| KeepAlive names | p50 (us) | floor: GetEnv p50 (us) | ratio |")
    print("|---|---|---|---|")
    for count, (ours, floors) in rows.items():
        ratio = statistics.median(o / f for o, f in zip(ours, floors))
        print(f"| {count} | {statistics.median(ours):.0f} | {statistics.median(floors):.0f} | {ratio:.2f}x |")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
