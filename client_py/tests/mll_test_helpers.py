"""Helpers shared by the client's tests (a uniquely named module rather than conftest, since
pytest runs this suite beside examples/dqn/tests, which has its own conftest)."""

import contextlib
import os
import pathlib
import re
import shutil
import signal
import socket
import subprocess
import time
import urllib.request

import grpc
import numpy as np
import pytest
from grpc_health.v1 import health_pb2, health_pb2_grpc

import multi_lunar_lander as mll
from multi_lunar_lander._stubs import pb, pb_grpc


def run_heuristic_parallel(env, seed):
    """Flies every lander of a parallel env with the heuristic for one episode; returns per-agent
    lists of the observations each agent acted on, and the final infos."""
    observations, _ = env.reset(seed=seed)
    seen = {agent: [obs] for agent, obs in observations.items()}
    final = {}
    while env.agents:
        actions = {agent: mll.heuristic(observations[agent], env.continuous) for agent in env.agents}
        observations, _, terminations, truncations, infos = env.step(actions)
        for agent in observations:
            if terminations[agent] or truncations[agent]:
                final[agent] = infos[agent]
            else:
                seen[agent].append(observations[agent])
    return seen, final


def raises_code(code, call, *args, **kwargs):
    """The MLLError that call(*args, **kwargs) raises, checked to carry `code` and a message."""
    with pytest.raises(mll.MLLError) as caught:
        call(*args, **kwargs)
    assert caught.value.code == code, caught.value
    assert caught.value.message
    return caught.value


def delete_env(raw_stub, name):
    raw_stub.DeleteEnv(pb.DeleteEnvRequest(name=name))


def assert_not_found(raw_stub, name):
    with pytest.raises(grpc.RpcError) as caught:
        raw_stub.GetEnv(pb.GetEnvRequest(name=name))
    assert caught.value.code() == grpc.StatusCode.NOT_FOUND


def listed_names(address):
    """Every env name the server at `address` lists (all pages), through a plain stub."""
    names, token = set(), ""
    with grpc.insecure_channel(address) as channel:
        stub = pb_grpc.MultiLunarLanderStub(channel)
        while True:
            page = stub.ListEnvs(pb.ListEnvsRequest(page_size=7, page_token=token), timeout=10)
            names.update(env.name for env in page.envs)
            token = page.next_page_token
            if not token:
                return names


def wait_draining(address, timeout_s=10):
    """Waits (bounded) until the server at `address` answers its health check NOT_SERVING: it
    got SIGTERM and drains."""
    deadline = time.monotonic() + timeout_s
    with grpc.insecure_channel(address) as channel:
        stub = health_pb2_grpc.HealthStub(channel)
        while stub.Check(health_pb2.HealthCheckRequest(), timeout=5).status != health_pb2.HealthCheckResponse.NOT_SERVING:
            assert time.monotonic() < deadline, f"the server at {address} does not drain within {timeout_s} s"
            time.sleep(0.02)


def url_in_log(process, pattern, timeout_s=10):
    """The URL a ServerProcess logged at start-up (group 1 of `pattern`), e.g. where its
    --metrics_address or --http_address with port 0 listens."""
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        found = re.search(pattern, process.log_tail(100000))
        if found:
            return found.group(1)
        time.sleep(0.02)
    raise AssertionError(f"nothing matches {pattern!r} in the log: {process.log_tail()!r}")


def metrics_url(process):
    """The /metrics URL a ServerProcess logged at start-up (its --metrics_address had port 0)."""
    return url_in_log(process, r"metrics on (http://\S+/metrics)")


def metric(url, series):
    """The value of one series, e.g. 'mll_steps_total{method="StepBatch"}', scraped from `url`."""
    with urllib.request.urlopen(url, timeout=10) as reply:
        for line in reply.read().decode().splitlines():
            if line.startswith(series + " "):
                return float(line.split()[-1])
    raise AssertionError(f"{series} not in {url}")


def random_actions(rng, shape, continuous):
    if continuous:
        return rng.uniform(-1.0, 1.0, size=shape + (2,)).astype(np.float32)
    return rng.integers(0, 4, size=shape, dtype=np.int32)


def same_bits(got, expected):
    """Equal bit for bit (unlike ==, tells -0.0 from 0.0), with the same dtype."""
    got, expected = np.asarray(got), np.asarray(expected, dtype=np.asarray(got).dtype)
    return got.shape == expected.shape and got.tobytes() == expected.tobytes()


def rollout(vector, seed, steps):
    """Every array a vector env returns over `steps` random steps after reset(seed)."""
    rng = np.random.default_rng(seed)
    observations, infos = vector.reset(seed=seed)
    record = [observations, *(infos[key] for key in sorted(infos))]
    for _ in range(steps):
        result = vector.step(random_actions(rng, (vector.num_envs, vector.n_landers), vector.continuous))
        record.extend(result[:-1])
        record.extend(result[-1][key] for key in sorted(result[-1]))
    return record


def check_against_parallel_envs(vector, seed, steps):
    """Steps `vector` as rollout does (reset(seed), then `steps` random steps) beside one
    parallel_env per env with the same options, seeds and actions (a code path of its own: unary
    grpcio calls, no vector engine) and checks every row against them bit for bit: each
    transition (active) row's reward, termination and truncation, and observation while the lander
    flies on; each auto-reset row's new episode (an unseeded reset of the parallel env); and that
    a row is active exactly when the parallel env's lander acted. Returns how many auto-resets
    there were."""
    options = dict(vector.config, address=vector.address)
    envs = [mll.parallel_env(**options) for _ in range(vector.num_envs)]
    agents = vector.possible_agents
    rng = np.random.default_rng(seed)
    auto_resets = 0
    try:
        observations, _ = vector.reset(seed=seed)
        for i, env in enumerate(envs):
            expected, _ = env.reset(seed=seed + i)
            assert all(same_bits(observations[i, k], expected[agent]) for k, agent in enumerate(agents))
        for _ in range(steps):
            actions = random_actions(rng, (vector.num_envs, vector.n_landers), vector.continuous)
            observations, rewards, terminations, truncations, active, infos = vector.step(actions)
            for i, env in enumerate(envs):
                if not env.agents:  # Its episode was over: the vector env started the next one.
                    expected, _ = env.reset()
                    assert infos["auto_reset"][i] and not active[i].any()
                    assert all(same_bits(observations[i, k], expected[agent]) for k, agent in enumerate(agents))
                    auto_resets += 1
                    continue
                assert not infos["auto_reset"][i]
                obs, rew, term, trunc, _ = env.step({agent: actions[i, k] for k, agent in enumerate(agents)
                                                     if agent in env.agents})
                for k, agent in enumerate(agents):
                    assert active[i, k] == (agent in rew)
                    if agent not in rew:
                        continue
                    assert same_bits(rewards[i, k], np.float32(rew[agent]))
                    assert (terminations[i, k], truncations[i, k]) == (term[agent], trunc[agent])
                    if not (term[agent] or trunc[agent]):
                        assert same_bits(observations[i, k], obs[agent])
                assert infos["episode_over"][i] == (not env.agents)
    finally:
        for env in envs:
            env.close()
    return auto_resets


@contextlib.contextmanager
def stopped(server):
    """The server stopped (SIGSTOP: its sockets stay open, it answers nothing) once every thread
    reads as stopped (at most 10 s); continued (SIGCONT) on leaving, whatever happened."""
    os.kill(server.pid, signal.SIGSTOP)
    try:
        tasks = pathlib.Path(f"/proc/{server.pid}/task")
        deadline = time.monotonic() + 10
        while time.monotonic() < deadline:
            states = [(task / "stat").read_text().rsplit(")", 1)[1].split()[0] for task in tasks.iterdir()]
            if all(state in "Tt" for state in states):
                break
            time.sleep(0.001)
        yield
    finally:
        os.kill(server.pid, signal.SIGCONT)


def holds_no_env_within(address, seconds):
    """Whether the server at `address` lists no env within `seconds` (polled)."""
    deadline = time.monotonic() + seconds
    while time.monotonic() < deadline:
        if not listed_names(address):
            return True
        time.sleep(0.1)
    return False


def free_port_on(*hosts):
    """A TCP port free on every one of `hosts` (loopback addresses such as 127.0.0.2), for
    servers that share a port behind one name."""
    for _ in range(50):
        with socket.socket() as probe:
            probe.bind((hosts[0], 0))
            port = probe.getsockname()[1]
        try:
            for host in hosts:
                with socket.socket() as other:
                    other.bind((host, port))
        except OSError:
            continue
        return port
    raise RuntimeError(f"no port free on all of {hosts}")


@contextlib.contextmanager
def server_at(host, port, extra_args=(), startup_timeout_s=30, tls=None):
    """An mll_server listening on `host`:`port` (e.g. 127.0.0.2, for several servers behind one
    name), up and SERVING (`tls`: (root certificate path, server name) for a server with TLS
    flags); stopped (SIGTERM, then SIGKILL) at the end. Yields the Popen."""
    from multi_lunar_lander._channel import Security
    from multi_lunar_lander._server import wait_until_serving

    security = Security.from_options(*tls) if tls else Security()

    process = subprocess.Popen(
        [mll.find_server_binary(), f"--address={host}:{port}", "--threads=1", *extra_args],
        stdin=subprocess.DEVNULL, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
    )
    try:
        wait_until_serving(f"{host}:{port}", startup_timeout_s, security)
        yield process
    finally:
        if process.poll() is None:
            process.terminate()
            try:
                process.wait(timeout=10)
            except subprocess.TimeoutExpired:
                process.kill()
                process.wait()


def write_hosts(path, names):
    """Writes a hosts file mapping each name of `names` ({name: [ip, ...]}) to its addresses, in
    place (the same inode), so a namespace that bind-mounted it as /etc/hosts sees the change at
    once."""
    text = "127.0.0.1 localhost\n" + "".join(f"{ip} {name}\n" for name, ips in names.items() for ip in ips)
    with open(path, "w") as file:
        file.write(text)


def run_with_hosts(hosts_file, argv, timeout_s=120):
    """Runs `argv` in a private mount namespace (unshare -m) whose /etc/hosts is `hosts_file`
    bind-mounted: names the test resolves, without touching the machine's /etc/hosts. Skips the
    test, saying why, where unshare -m is not permitted. Returns the CompletedProcess, its
    stdout and stderr together in `stdout`."""
    if shutil.which("unshare") is None:
        pytest.skip("unshare (util-linux) is not installed: no private mount namespace for a hosts file")
    probe = subprocess.run(["unshare", "-m", "true"], capture_output=True, text=True)
    if probe.returncode != 0:
        pytest.skip(f"unshare -m is not permitted here ({probe.stderr.strip()}): no private hosts file")
    script = 'mount --bind "$0" /etc/hosts && exec "$@"'
    return subprocess.run(
        ["unshare", "-m", "sh", "-c", script, str(hosts_file), *map(str, argv)],
        stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, timeout=timeout_s,
    )


def quota_and_roomy_servers(tmp_path, tenants, max_envs_per_token, max_envs=20):
    """Two servers (not started) that accept the bearer tokens `tenants`, each hosting at most
    `max_envs` envs; the first also bounds each token to `max_envs_per_token` envs there."""
    tokens = tmp_path / "tokens"
    tokens.write_text("".join(f"{tenant}\n" for tenant in tenants))
    auth = (f"--auth_token_file={tokens}", f"--max_envs={max_envs}")
    quota = mll.ServerProcess(threads=1, extra_args=(*auth, f"--max_envs_per_token={max_envs_per_token}"))
    return quota, mll.ServerProcess(threads=1, extra_args=auth)


def without_log_files(model):
    """`model` (an SB3 algorithm) with a logger that writes nothing: without one of its own, each
    learn() makes an empty SB3-<time> directory in the system's temporary directory."""
    from stable_baselines3.common.logger import Logger

    model.set_logger(Logger(folder=None, output_formats=[]))
    return model
