"""One real mll_server per test session, on a free loopback port ($MLL_SERVER_BIN, else PATH,
else the repository's build tree). Tests that exercise the embedded default start their own."""

import os

os.environ.setdefault("SDL_VIDEODRIVER", "dummy")  # render_mode="human" without a display.
os.environ.setdefault("SDL_AUDIODRIVER", "dummy")

import grpc
import pytest

import multi_lunar_lander as mll
from multi_lunar_lander._stubs import pb, pb_grpc


@pytest.fixture(scope="session")
def server():
    with mll.ServerProcess(threads=2) as process:
        yield process


@pytest.fixture(scope="session")
def address(server):
    return server.address


@pytest.fixture(scope="session")
def raw_stub(address):
    """A plain gRPC stub, to look at the server behind the client's back."""
    with grpc.insecure_channel(address) as channel:
        yield pb_grpc.MultiLunarLanderStub(channel)


@pytest.fixture(params=[False, True], ids=["discrete", "continuous"])
def continuous(request):
    return request.param


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


def delete_env(raw_stub, name):
    raw_stub.DeleteEnv(pb.DeleteEnvRequest(name=name))


def assert_not_found(raw_stub, name):
    with pytest.raises(grpc.RpcError) as caught:
        raw_stub.GetEnv(pb.GetEnvRequest(name=name))
    assert caught.value.code() == grpc.StatusCode.NOT_FOUND
