#!/usr/bin/env python3
"""The figures a Kubernetes pod of mll_server is sized and autoscaled by (docs/deployment.md,
"Autoscaling"): its CPU per 1,000 agent-steps/s, its CPU per hosted idle environment, its
memory idle and per environment, and what GetServerInfo's load reports meanwhile.

Starts `mll_server --threads=T --max_envs=M` on loopback with /metrics, then:
1. memory idle: its resident memory (/proc/<pid>/status VmRSS) once started;
2. load: `mll_cli bench --clients=C --envs=E --n_landers=L --transport=native` (the gRPC stream,
   as a trainer on another host uses it) for --seconds; the server's CPU (/metrics
   process_cpu_seconds_total) and agent-steps (mll_agent_steps_total) over the run without its
   first and last second; GetServerInfo's load (mll_cli info) asked in the middle, its cpu_cores
   and agent_steps_per_s beside the window's;
3. hosting: creates and resets N idle environments of L landers (N = --hosted, default M), reads
   the resident memory again (per environment: the difference over N) and the server's CPU over
   --idle_seconds with nothing stepping (per hosted environment).

Loopback only, every phase bounded in time. Prints one JSON line.

    .venv/bin/python bench/service/pod_sizing.py
"""

from __future__ import annotations

import argparse
import json
import pathlib
import subprocess
import sys
import threading
import time

REPO = pathlib.Path(__file__).resolve().parents[2]
sys.path.insert(0, str(REPO / "bench" / "service"))
sys.path.insert(0, str(REPO / "client_py"))
from bench_server_cpu import Server  # noqa: E402


def resident_mib(pid: int) -> float:
    for line in pathlib.Path(f"/proc/{pid}/status").read_text().splitlines():
        if line.startswith("VmRSS:"):
            return int(line.split()[1]) / 1024
    raise RuntimeError("no VmRSS")


def server_load(cli: str, address: str) -> dict:
    out = subprocess.run([cli, "info", f"--address={address}"], capture_output=True, text=True, timeout=30,
                         check=True).stdout
    return json.loads(out.splitlines()[0])["load"]


def host_idle_envs(address: str, count: int, n_landers: int) -> None:
    """Creates and resets `count` environments over the raw stubs (they stay on the server)."""
    import grpc

    from multi_lunar_lander._stubs import pb, pb_grpc

    stub = pb_grpc.MultiLunarLanderStub(grpc.insecure_channel(address))
    for i in range(count):
        env = stub.CreateEnv(pb.CreateEnvRequest(config=pb.EnvConfig(n_landers=n_landers)), timeout=30)
        stub.ResetEnv(pb.ResetEnvRequest(name=env.name, seed=i), timeout=30)


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--binary", default=str(REPO / "build/server/service/mll_server"))
    parser.add_argument("--cli", default=str(REPO / "build/client_cpp/mll_cli"))
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--max_envs", type=int, default=2048)
    parser.add_argument("--clients", type=int, default=2)
    parser.add_argument("--envs", type=int, default=64)
    parser.add_argument("--n_landers", type=int, default=3)
    parser.add_argument("--seconds", type=float, default=8.0)
    parser.add_argument("--hosted", type=int, default=None, help="idle environments to host (default --max_envs)")
    parser.add_argument("--idle_seconds", type=float, default=10.0)
    args = parser.parse_args()
    hosted = args.max_envs if args.hosted is None else args.hosted

    server = Server(args.binary, args.threads, None)
    try:
        # Server() starts it with --max_envs=100000; the bound only refuses, it allocates nothing.
        time.sleep(1.0)
        idle_mib = resident_mib(server.pid)

        bench = subprocess.Popen(
            [args.cli, "bench", f"--address={server.address}", f"--clients={args.clients}", f"--envs={args.envs}",
             f"--n_landers={args.n_landers}", f"--seconds={args.seconds}", "--transport=native"],
            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
        )
        time.sleep(1.0)
        first = server.scrape()
        reported = {}
        probe = threading.Timer((args.seconds - 2) / 2, lambda: reported.update(server_load(args.cli, server.address)))
        probe.start()
        time.sleep(args.seconds - 2.0)
        last = server.scrape()
        probe.join()
        out, err = bench.communicate(timeout=args.seconds + 60)
        if bench.returncode != 0:
            raise RuntimeError(f"mll_cli bench failed: {err}")
        window_s = args.seconds - 2.0
        cpu_s = last["cpu_s"] - first["cpu_s"]
        agent_steps = last["agent_steps"] - first["agent_steps"]
        cores_per_1000 = cpu_s / agent_steps * 1000 if agent_steps else float("nan")

        before = resident_mib(server.pid)
        host_idle_envs(server.address, hosted, args.n_landers)
        time.sleep(1.0)
        full_mib = resident_mib(server.pid)
        idle_first = server.scrape()
        time.sleep(args.idle_seconds)
        idle_last = server.scrape()
        idle_cores = (idle_last["cpu_s"] - idle_first["cpu_s"]) / args.idle_seconds
        result = {
            "threads": args.threads,
            "clients": args.clients,
            "envs_per_client": args.envs,
            "n_landers": args.n_landers,
            "bench": json.loads(out.splitlines()[-1]),
            "window_s": window_s,
            "server_cores": round(cpu_s / window_s, 3),
            "agent_steps_per_s": round(agent_steps / window_s),
            "cores_per_1000_agent_steps_per_s": round(cores_per_1000, 4),
            "server_info_load_mid_run": reported,
            "rss_idle_mib": round(idle_mib, 1),
            "hosted_envs": hosted,
            "rss_hosting_mib": round(full_mib, 1),
            "kib_per_env": round((full_mib - before) * 1024 / hosted, 1),
            "idle_hosting_cores": round(idle_cores, 4),
            "cores_per_1000_idle_envs": round(idle_cores / hosted * 1000, 4),
        }
        print(json.dumps(result))
    finally:
        server.close()
    return 0


if __name__ == "__main__":
    sys.exit(main())
