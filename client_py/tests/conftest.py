"""One real mll_server per test session, on a free loopback port ($MLL_SERVER_BIN, else PATH,
else the repository's build tree). Tests that exercise the embedded default start their own."""

import os

os.environ.setdefault("SDL_VIDEODRIVER", "dummy")  # render_mode="human" without a display.
os.environ.setdefault("SDL_AUDIODRIVER", "dummy")

import grpc
import pytest

import multi_lunar_lander as mll
from multi_lunar_lander._stubs import pb_grpc


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
