"""Discovery and least-loaded placement of the PettingZoo envs (env, parallel_env): servers on
127.0.0.2 and 127.0.0.3 behind one name, as a Kubernetes headless Service's name resolves to its
pods. The name lives in a hosts file bind-mounted as /etc/hosts in a private mount namespace
(mll_test_helpers.run_with_hosts); the test bodies run there as this file run as a script, the
servers outside it (the network is the same).

- placement: one server half full of another tenant's envs; the trainer's envs go to the other.
- failover: the env's server dies after a second server joined the name; failover resolves the
  name again and moves the env there, every step the same bits as an undisturbed env.
- TLS: the certificate names the name, not the addresses; the env checks it against the name.
- every server full: RESOURCE_EXHAUSTED naming each (a plain list, no name needed).
"""

import json
import os
import pickle
import signal
import subprocess
import sys

import numpy as np
import pytest

import multi_lunar_lander as mll
from mll_test_helpers import free_port_on, quota_and_roomy_servers, run_with_hosts, server_at, write_hosts

NAME = "fleet.test"
A, B = "127.0.0.2", "127.0.0.3"
TENANT, TRAINER = "tenant-7f3c2a91", "trainer-19d2b6e0"


def _run_body(hosts_file, body, *args):
    result = run_with_hosts(hosts_file, [sys.executable, __file__, body, json.dumps(args)])
    assert result.returncode == 0, result.stdout[-4000:]


def test_new_envs_go_to_the_server_without_another_tenants_envs(tmp_path):
    token_file = tmp_path / "tokens"
    token_file.write_text(f"{TENANT}\n{TRAINER}\n")
    port = free_port_on(A, B)
    flags = ("--max_envs=8", f"--auth_token_file={token_file}")  # 4 envs per token.
    with server_at(A, port, flags), server_at(B, port, flags):
        # The other tenant fills its quota on A: A is half full.
        others = [mll.parallel_env(address=f"{A}:{port}", token=TENANT, n_landers=1) for _ in range(4)]
        hosts = tmp_path / "hosts"
        write_hosts(hosts, {NAME: [A, B]})
        _run_body(hosts, "placement", port)
        for env in others:
            env.close()


def placement(port):
    name = f"{NAME}:{port}"
    envs = [mll.parallel_env(address=name, token=TRAINER, n_landers=2) for _ in range(2)]
    envs.append(mll.env(address=name, token=TRAINER, n_landers=2))
    # B held none, A 4 of 8: B takes each (1/8, 2/8, 3/8 against A's 5/8).
    assert [env.address for env in envs] == [f"{B}:{port}"] * 3, [env.address for env in envs]
    assert all(env.failover for env in envs)  # A name may stand for several servers.
    a = mll.server_info(f"{A}:{port}", token=TRAINER)
    assert a.load.envs_hosted == 4 and a.limits.max_envs == 8
    envs[0].reset(seed=1)
    envs[0].step({agent: 0 for agent in envs[0].agents})
    for env in envs:
        env.close()


def test_no_server_with_room_is_resource_exhausted_naming_each():
    with mll.ServerProcess(threads=1, max_envs=1) as a, mll.ServerProcess(threads=1, max_envs=1) as b:
        held = [mll.parallel_env(address=[a.address, b.address], n_landers=1) for _ in range(2)]
        assert sorted(env.address for env in held) == sorted([a.address, b.address])
        with pytest.raises(mll.MLLError) as caught:
            mll.parallel_env(address=[a.address, b.address], n_landers=1)
        assert caught.value.code.name == "RESOURCE_EXHAUSTED"
        for server in (a, b):
            assert f"{server.address}: full (1 of --max_envs=1)" in caught.value.message, caught.value.message
        for env in held:
            env.close()


def test_a_token_quota_reached_on_the_least_loaded_server_passes_it_over(tmp_path):
    """Placement reads envs hosted against --max_envs, which a per-token quota does not show: the
    least-loaded server answers RESOURCE_EXHAUSTED once the token's quota there is reached, and
    the env goes to the next one."""
    quota, roomy = quota_and_roomy_servers(tmp_path, ["tenant-a", "tenant-b"], max_envs_per_token=1)
    with quota, roomy:
        addresses = [quota.address, roomy.address]
        # Another tenant's 3 envs keep the quota server the least loaded for tenant-a's first 3
        # envs: the first lands there, the next two are refused there and go to the other.
        theirs = [mll.parallel_env(address=roomy.address, token="tenant-b", n_landers=1) for _ in range(3)]
        ours = [mll.parallel_env(address=addresses, token="tenant-a", n_landers=1) for _ in range(3)]
        assert [env.address for env in ours] == [quota.address, roomy.address, roomy.address]
        ours[-1].reset(seed=3)
        ours[-1].step({agent: 0 for agent in ours[-1].agents})
        for env in ours + theirs:
            env.close()


def test_failover_resolves_the_name_again(tmp_path):
    port = free_port_on(A, B)
    with server_at(A, port) as a, server_at(B, port):
        hosts = tmp_path / "hosts"
        write_hosts(hosts, {NAME: [A]})
        _run_body(hosts, "failover", port, str(hosts), a.pid)


def failover(port, hosts, pid_a):
    env = mll.parallel_env(address=f"{NAME}:{port}", n_landers=2)
    reference = mll.parallel_env(address=f"{B}:{port}", n_landers=2)
    assert env.address == f"{A}:{port}"
    rng = np.random.default_rng(4)
    for e in (env, reference):
        e.reset(seed=4)
    for step in range(60):
        if step == 30:
            # B joins the name, then A dies: only a new resolution finds B.
            write_hosts(hosts, {NAME: [A, B]})
            os.kill(pid_a, signal.SIGKILL)
        if not reference.agents:
            for e in (env, reference):
                e.reset()
        actions = {agent: int(rng.integers(4)) for agent in reference.agents}
        got, want = env.step(actions), reference.step(actions)
        assert pickle.dumps(got) == pickle.dumps(want), step
    assert env.failovers == 1 and env.address == f"{B}:{port}"
    # Every server of the name gone: a clear error naming the name.
    write_hosts(hosts, {})
    with pytest.raises(mll.MLLError) as caught:
        mll.parallel_env(address=f"{NAME}:{port}", n_landers=2)
    assert caught.value.code.name == "UNAVAILABLE" and NAME in caught.value.message, caught.value.message
    for e in (env, reference):
        e.close()


def test_tls_checks_the_certificate_against_the_name(tmp_path):
    if subprocess.run(["sh", "-c", "command -v openssl"], capture_output=True).returncode != 0:
        pytest.skip("openssl is missing: no certificate to make")
    cert, key = tmp_path / "fleet.crt", tmp_path / "fleet.key"
    subprocess.run(
        ["openssl", "req", "-x509", "-newkey", "ec", "-pkeyopt", "ec_paramgen_curve:prime256v1", "-nodes",
         "-days", "1", "-subj", f"/CN={NAME}", "-addext", f"subjectAltName=DNS:{NAME}",
         "-keyout", str(key), "-out", str(cert)],
        check=True, capture_output=True, timeout=60,
    )
    port = free_port_on(A, B)
    flags = (f"--tls_cert={cert}", f"--tls_key={key}")
    with server_at(A, port, flags, tls=(str(cert), NAME)), server_at(B, port, flags, tls=(str(cert), NAME)):
        hosts = tmp_path / "hosts"
        write_hosts(hosts, {NAME: [A, B]})
        _run_body(hosts, "tls", port, str(cert))


def tls(port, cert):
    envs = [mll.parallel_env(address=f"{NAME}:{port}", tls_root_cert=cert, n_landers=1) for _ in range(2)]
    # Dialled by address, checked by name; one on each (both empty, then 1/N against 0).
    assert sorted(env.address for env in envs) == [f"{A}:{port}", f"{B}:{port}"]
    for env in envs:
        env.reset(seed=2)
        env.close()


if __name__ == "__main__":
    globals()[sys.argv[1]](*json.loads(sys.argv[2]))
