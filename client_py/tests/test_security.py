"""TLS and bearer tokens against real servers: a self-signed certificate made at test time with
the openssl CLI (Debian's `openssl`, installed by scripts/setup.sh), servers started with
--tls_cert/--tls_key and --auth_token_file."""

import shutil
import subprocess

import grpc
import numpy as np
import pytest

import multi_lunar_lander as mll
from multi_lunar_lander import _remote
from multi_lunar_lander._channel import Security
from multi_lunar_lander._stubs import pb

from mll_test_helpers import raises_code as _error

# The name in the test certificate: not the dialled 127.0.0.1, so tls_server_name is needed.
SERVER_NAME = "mll-server.test"
TOKEN_A = "token-a-Zx81"
TOKEN_B = "token-b-Qw27"


def _server_flags():
    binary = mll.find_server_binary()
    help_text = subprocess.run([binary, "--help"], capture_output=True, text=True, timeout=30)
    return help_text.stdout + help_text.stderr


_FLAGS = _server_flags()
needs_tls = pytest.mark.skipif(
    "--tls_cert" not in _FLAGS or shutil.which("openssl") is None,
    reason="this mll_server has no --tls_cert flag (or openssl is missing)",
)
needs_auth = pytest.mark.skipif(
    "--auth_token_file" not in _FLAGS, reason="this mll_server has no --auth_token_file flag"
)


def self_signed(directory, name):
    """(certificate path, key path) of a fresh self-signed EC certificate for DNS name `name`."""
    cert, key = directory / f"{name}.crt", directory / f"{name}.key"
    subprocess.run(
        ["openssl", "req", "-x509", "-newkey", "ec", "-pkeyopt", "ec_paramgen_curve:prime256v1",
         "-nodes", "-days", "1", "-subj", f"/CN={name}", "-addext", f"subjectAltName=DNS:{name}",
         "-keyout", str(key), "-out", str(cert)],
        check=True, capture_output=True, timeout=60,
    )
    return cert, key


@pytest.fixture(scope="module")
def certificate(tmp_path_factory):
    return self_signed(tmp_path_factory.mktemp("tls"), SERVER_NAME)


@pytest.fixture(scope="module")
def token_file(tmp_path_factory):
    path = tmp_path_factory.mktemp("auth") / "tokens"
    path.write_text(f"# two trainers\n{TOKEN_A}\n\n{TOKEN_B}\n")
    return path


@pytest.fixture(scope="module")
def tls_server(certificate):
    cert, key = certificate
    with mll.ServerProcess(
        threads=1, extra_args=(f"--tls_cert={cert}", f"--tls_key={key}"),
        tls_root_cert=str(cert), tls_server_name=SERVER_NAME,
    ) as process:
        yield process.address


@pytest.fixture(scope="module")
def auth_server(token_file):
    with mll.ServerProcess(threads=1, extra_args=(f"--auth_token_file={token_file}",)) as process:
        yield process.address


@pytest.fixture(scope="module")
def tls_auth_servers(certificate, token_file):
    cert, key = certificate
    flags = (f"--tls_cert={cert}", f"--tls_key={key}", f"--auth_token_file={token_file}")
    with mll.ServerProcess(threads=1, extra_args=flags, tls_root_cert=str(cert), tls_server_name=SERVER_NAME) as a, \
            mll.ServerProcess(threads=1, extra_args=flags, tls_root_cert=str(cert), tls_server_name=SERVER_NAME) as b:
        yield a.address, b.address


@pytest.fixture
def no_env_token(monkeypatch):
    monkeypatch.delenv(mll.TOKEN_ENV, raising=False)


@needs_tls
def test_tls_client_flies_and_matches_a_plaintext_server(tls_server, certificate, address):
    cert = certificate[0]
    secure = mll.parallel_env(address=tls_server, tls_root_cert=str(cert), tls_server_name=SERVER_NAME, n_landers=2)
    plain = mll.parallel_env(address=address, n_landers=2)
    for env in (secure, plain):
        env.reset(seed=5)
    for _ in range(20):
        actions = {agent: 1 for agent in secure.agents}
        ours, reference = secure.step(actions), plain.step(actions)
        for agent in ours[0]:
            np.testing.assert_array_equal(ours[0][agent], reference[0][agent])
    assert secure.render_mode is None
    secure.close()
    plain.close()
    # PEM bytes work as well as a path.
    aec = mll.env(address=tls_server, tls_root_cert=cert.read_bytes(), tls_server_name=SERVER_NAME)
    aec.reset(seed=1)
    aec.close()


@needs_tls
def test_plaintext_client_of_a_tls_server_fails_cleanly(tls_server):
    error = _error(grpc.StatusCode.UNAVAILABLE, mll.parallel_env, address=tls_server)
    assert tls_server in error.message and "plaintext" in error.message


@needs_tls
def test_tls_needs_the_right_root_and_name(tls_server, certificate, tmp_path):
    cert = certificate[0]
    # The certificate is for SERVER_NAME, not for the dialled 127.0.0.1.
    error = _error(grpc.StatusCode.UNAVAILABLE, mll.parallel_env, address=tls_server, tls_root_cert=str(cert))
    assert tls_server in error.message and "TLS" in error.message
    other, _ = self_signed(tmp_path, SERVER_NAME)  # Same name, another key: not trusted.
    _error(
        grpc.StatusCode.UNAVAILABLE, mll.parallel_env,
        address=tls_server, tls_root_cert=str(other), tls_server_name=SERVER_NAME,
    )


@pytest.mark.parametrize(
    "kwargs, field",
    [
        (dict(tls_root_cert="/nonexistent/ca.pem"), "tls_root_cert"),
        (dict(tls_root_cert=b"not a certificate"), "tls_root_cert"),
        (dict(tls_root_cert=42), "tls_root_cert"),
        (dict(tls_server_name=SERVER_NAME), "tls_server_name"),
        (dict(token="has space"), "token"),
        (dict(token=7), "token"),
    ],
)
def test_bad_security_options_are_invalid_argument(kwargs, field):
    error = _error(grpc.StatusCode.INVALID_ARGUMENT, mll.parallel_env, address="127.0.0.1:1", **kwargs)
    assert field in error.message
    assert "has space" not in error.message  # A token is never echoed.


def test_the_token_stays_out_of_reprs_and_errors(monkeypatch):
    security = Security.from_options(token=TOKEN_A)
    assert security.metadata == (("authorization", f"Bearer {TOKEN_A}"),)
    assert TOKEN_A not in repr(security) and TOKEN_A not in security.describe()
    monkeypatch.setenv(mll.TOKEN_ENV, "two words")
    error = _error(grpc.StatusCode.INVALID_ARGUMENT, Security.from_options)
    assert mll.TOKEN_ENV in error.message and "two words" not in error.message


def test_tls_with_the_embedded_server_is_refused(certificate):
    error = _error(grpc.StatusCode.INVALID_ARGUMENT, mll.vector_env, 1, tls_root_cert=str(certificate[0]))
    assert "tls_root_cert" in error.message and "embedded" in error.message


@needs_auth
def test_right_token_works_missing_or_wrong_is_unauthenticated(auth_server, no_env_token):
    env = mll.parallel_env(address=auth_server, token=TOKEN_A)
    env.reset(seed=0)
    env.close()
    error = _error(grpc.StatusCode.UNAUTHENTICATED, mll.parallel_env, address=auth_server)
    assert "authorization" in error.message  # The server's message, passed through.
    error = _error(grpc.StatusCode.UNAUTHENTICATED, mll.vector_env, 2, address=auth_server, token="wrong-token")
    assert "wrong-token" not in error.message


@needs_auth
def test_token_comes_from_the_environment_unless_given(auth_server, monkeypatch):
    monkeypatch.setenv(mll.TOKEN_ENV, TOKEN_B + "\n")  # As read from a file; whitespace is dropped.
    env = mll.env(address=auth_server)  # $MLL_TOKEN.
    env.reset(seed=0)
    env.close()
    _error(grpc.StatusCode.UNAUTHENTICATED, mll.env, address=auth_server, token="")  # "" sends none.
    _error(grpc.StatusCode.UNAUTHENTICATED, mll.env, address=auth_server, token="not-a-token")  # token= wins.


@needs_auth
def test_envs_of_one_token_are_not_found_for_another(auth_server, no_env_token):
    env = mll.parallel_env(address=auth_server, token=TOKEN_A)
    env.reset(seed=2)
    as_b = _remote.Connection(auth_server, Security(token=TOKEN_B))
    as_a = _remote.Connection(auth_server, Security(token=TOKEN_A))
    error = _error(grpc.StatusCode.NOT_FOUND, as_b.call, "ResetEnv", pb.ResetEnvRequest(name=env.name))
    assert env.name in error.message
    _error(grpc.StatusCode.NOT_FOUND, as_b.call, "DeleteEnv", pb.DeleteEnvRequest(name=env.name))
    assert env.name not in {e.name for e in as_b.call("ListEnvs", pb.ListEnvsRequest()).envs}
    assert env.name in {e.name for e in as_a.call("ListEnvs", pb.ListEnvsRequest()).envs}
    env.step({agent: 0 for agent in env.agents})  # Untouched by B's attempts.
    env.close()
    as_a.close()
    as_b.close()


@needs_tls
@needs_auth
def test_vector_env_over_two_tls_token_servers_matches_one_plaintext_server(tls_auth_servers, certificate, address):
    options = dict(n_landers=2, max_cycles=30)
    spread = mll.vector_env(
        4, address=list(tls_auth_servers), tls_root_cert=str(certificate[0]),
        tls_server_name=SERVER_NAME, token=TOKEN_A, **options,
    )
    assert set(spread.env_addresses) == set(tls_auth_servers)  # Placed by load, both used.
    single = mll.vector_env(4, address=address, **options)
    observations, _ = spread.reset(seed=9)
    reference, _ = single.reset(seed=9)
    np.testing.assert_array_equal(observations, reference)
    for _ in range(40):  # Past max_cycles: auto-resets included.
        actions = mll.heuristic(observations, False)
        ours, theirs = spread.step(actions), single.step(actions)
        for got, expected in zip(ours[:-1], theirs[:-1]):
            np.testing.assert_array_equal(got, expected)
        observations = ours[0]
    spread.close()
    single.close()


@needs_tls
@needs_auth
def test_the_async_api_over_two_tls_token_servers_matches_one_plaintext_server(tls_auth_servers, certificate, address):
    options = dict(n_landers=2, max_cycles=30)
    with mll.vector_env(
        4, address=list(tls_auth_servers), tls_root_cert=str(certificate[0]),
        tls_server_name=SERVER_NAME, token=TOKEN_A, batch_size=2, **options,
    ) as spread, mll.vector_env(4, address=address, **options) as single:
        reference = [single.reset(seed=9)[0]]
        actions = np.tile(np.array([[2, 0]], np.int32), (4, 1))
        for _ in range(40):  # Past max_cycles: auto-resets included.
            reference.append(single.step(actions)[0])
        spread.async_reset(seed=9)
        seen = np.zeros(4, int)
        while seen.min() < 40:
            observations, *_, infos = spread.recv()
            for row, env in enumerate(infos["env_id"]):
                np.testing.assert_array_equal(observations[row], reference[seen[env]][env])
                seen[env] += 1
            spread.send(actions[: len(infos["env_id"])], infos["env_id"])


@needs_tls
@needs_auth
def test_a_pickled_env_keeps_tls_and_token_without_the_certificate_file(
    tls_auth_servers, certificate, tmp_path, monkeypatch
):
    """The pickle carries the root certificate's bytes, the name override and the token: the
    copy connects after the certificate file is gone and with $MLL_TOKEN set to another token."""
    import pickle

    cert_copy = tmp_path / "ca.pem"
    cert_copy.write_bytes(certificate[0].read_bytes())
    envs = [
        mll.parallel_env(address=tls_auth_servers[1], tls_root_cert=str(cert_copy), tls_server_name=SERVER_NAME,
                         token=TOKEN_A, n_landers=2),
        mll.gym_vector_env(2, address=list(tls_auth_servers), tls_root_cert=str(cert_copy),
                           tls_server_name=SERVER_NAME, token=TOKEN_A, n_landers=2),
    ]
    data = [pickle.dumps(env) for env in envs]
    cert_copy.unlink()
    monkeypatch.setenv(mll.TOKEN_ENV, TOKEN_B)
    parallel, vector = (pickle.loads(item) for item in data)
    assert parallel.address == tls_auth_servers[1]
    assert parallel.reset(seed=4)[0]["lander_0"].tobytes() == envs[0].reset(seed=4)[0]["lander_0"].tobytes()
    assert set(vector.vector.env_addresses) <= set(tls_auth_servers)  # Placed by load.
    assert vector.reset(seed=4)[0].tobytes() == envs[1].reset(seed=4)[0].tobytes()
    # Same token as the originals: the copies' envs belong to TOKEN_A, so TOKEN_B cannot see them.
    stranger = _remote.Connection(tls_auth_servers[1], Security.from_options(str(certificate[0]), SERVER_NAME, TOKEN_B))
    _error(grpc.StatusCode.NOT_FOUND, stranger.call, "GetEnv", pb.GetEnvRequest(name=parallel.name))
    stranger.close()
    for env in (parallel, vector, *envs):
        env.close()
