"""Flies environments on a running Multi Lunar Lander server and checks them.

Used by scripts/docker-test.sh (host -> container) and as the compose
trainer's default command (container -> server by service name). It flies two
environments with the same seed and the same scripted actions and checks that
their observations and rewards are the same bits, through
multi_lunar_lander.parallel_env when that package is installed, otherwise
through stubs generated from proto/ into a temporary directory (needs
grpcio-tools). Prints one summary line; exits non-zero on any failure.
"""

import argparse
import sys
import tempfile

import numpy as np

OBS_SIZE = 12  # docs/environment.md: 12 floats per lander.


def scripted_action(step, agent_index):
    """A fixed, varied discrete action: the same for both runs."""
    return (step + agent_index) % 4


def fly_with_package(address, n_landers, steps, seed):
    import multi_lunar_lander as mll

    if not hasattr(mll, "parallel_env"):
        raise ImportError("multi_lunar_lander has no parallel_env")
    env = mll.parallel_env(address=address, n_landers=n_landers)
    try:
        obs, _ = env.reset(seed=seed)
        trace = [np.stack([obs[a] for a in env.possible_agents])]
        for t in range(steps):
            if not env.agents:
                break
            actions = {a: scripted_action(t, env.possible_agents.index(a)) for a in env.agents}
            obs, rewards, _, _, _ = env.step(actions)
            trace.append(np.array([rewards[a] for a in sorted(rewards)], np.float32))
            trace.append(np.stack([obs[a] for a in sorted(obs)]))
    finally:
        env.close()
    return trace


def fly_vector_with_package(address, n_landers, steps, seed):
    """The first observations of vector_env(2) (env i seeded seed + i) after `steps` scripted
    steps, and its transport: the package's native engine, which the trainer image ships."""
    import multi_lunar_lander as mll

    with mll.vector_env(2, address=address, n_landers=n_landers) as envs:
        first, _ = envs.reset(seed=seed)
        for t in range(steps):
            actions = np.array([[scripted_action(t, i) for i in range(n_landers)]] * 2, np.int32)
            envs.step(actions)
        return first[0], envs.transport


def generated_stubs(proto_dir):
    from grpc_tools import protoc

    out = tempfile.mkdtemp(prefix="mll-stubs-")
    args = ["protoc", f"-I{proto_dir}", f"--python_out={out}", f"--grpc_python_out={out}",
            "mll/v1/multi_lunar_lander.proto"]
    if protoc.main(args) != 0:
        sys.exit(f"protoc failed on {proto_dir}")
    sys.path.insert(0, out)
    from mll.v1 import multi_lunar_lander_pb2, multi_lunar_lander_pb2_grpc

    return multi_lunar_lander_pb2, multi_lunar_lander_pb2_grpc


def fly_with_stubs(address, n_landers, steps, seed, proto_dir):
    import grpc

    pb, pb_grpc = generated_stubs(proto_dir)
    with grpc.insecure_channel(address) as channel:
        stub = pb_grpc.MultiLunarLanderStub(channel)
        config = pb.EnvConfig(n_landers=n_landers)
        env = stub.CreateEnv(pb.CreateEnvRequest(config=config), timeout=10)
        try:
            reset = stub.ResetEnv(pb.ResetEnvRequest(name=env.name, seed=seed), timeout=10)
            obs = np.frombuffer(reset.data.observations.data, "<f4").reshape(n_landers, OBS_SIZE)
            trace = [obs]
            for t in range(steps):
                actions = np.array([scripted_action(t, i) for i in range(n_landers)], "<i4")
                request = pb.StepEnvRequest(name=env.name, actions=pb.Array(
                    dtype=pb.DTYPE_INT32, shape=[n_landers], data=actions.tobytes()))
                data = stub.StepEnv(request, timeout=10).data
                trace.append(np.frombuffer(data.rewards.data, "<f4"))
                trace.append(np.frombuffer(data.observations.data, "<f4"))
                if data.episode_over:
                    break
        finally:
            stub.DeleteEnv(pb.DeleteEnvRequest(name=env.name), timeout=10)
    return trace


def leave_envs(address, n_landers, count, proto_dir):
    """Creates and resets `count` environments and leaves them on the server
    (its idle timeout reclaims them): for measuring memory per environment."""
    import grpc

    pb, pb_grpc = generated_stubs(proto_dir)
    with grpc.insecure_channel(address) as channel:
        stub = pb_grpc.MultiLunarLanderStub(channel)
        config = pb.EnvConfig(n_landers=n_landers)
        for seed in range(count):
            env = stub.CreateEnv(pb.CreateEnvRequest(config=config), timeout=10)
            stub.ResetEnv(pb.ResetEnvRequest(name=env.name, seed=seed), timeout=10)
    print(f"smoke_client: left {count} reset environments of {n_landers} landers at {address}")


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--address", required=True, help="host:port of the server")
    parser.add_argument("--n_landers", type=int, default=3)
    parser.add_argument("--steps", type=int, default=100)
    parser.add_argument("--seed", type=int, default=7)
    parser.add_argument("--proto_dir", default="proto", help="for the generated-stubs path")
    parser.add_argument("--stubs", action="store_true", help="skip the package, use stubs")
    parser.add_argument("--leave_envs", type=int, default=0,
                        help="only create and reset this many envs and leave them (stubs)")
    args = parser.parse_args()
    if args.leave_envs:
        leave_envs(args.address, args.n_landers, args.leave_envs, args.proto_dir)
        return

    def fly():
        if not args.stubs:
            try:
                return "multi_lunar_lander.parallel_env", fly_with_package(
                    args.address, args.n_landers, args.steps, args.seed)
            except ImportError as error:
                print(f"smoke_client: {error}; using stubs generated from {args.proto_dir}")
        return "stubs generated from proto/", fly_with_stubs(
            args.address, args.n_landers, args.steps, args.seed, args.proto_dir)

    (how, first), (_, second) = fly(), fly()
    if first[0].shape != (args.n_landers, OBS_SIZE):
        sys.exit(f"smoke_client: first observation has shape {first[0].shape}, "
                 f"want {(args.n_landers, OBS_SIZE)}")
    if len(first) != len(second) or not all(
            np.array_equal(a, b) for a, b in zip(first, second)):
        sys.exit("smoke_client: two runs with the same seed and actions differ")
    steps = (len(first) - 1) // 2
    print(f"smoke_client: {how} at {args.address}: 2 envs x {steps} steps, identical bits; "
          f"lander_0 first observation [{', '.join(f'{v:.3f}' for v in first[0][0])}]")
    if how.startswith("multi_lunar_lander"):
        vector_first, transport = fly_vector_with_package(args.address, args.n_landers, args.steps, args.seed)
        if not np.array_equal(vector_first, first[0]):
            sys.exit("smoke_client: vector_env's env 0 started elsewhere than parallel_env with the same seed")
        print(f"smoke_client: multi_lunar_lander.vector_env at {args.address} ({transport}): 2 envs x "
              f"{args.steps} steps; env 0 starts as parallel_env with the same seed")


if __name__ == "__main__":
    main()
