#!/usr/bin/env python3
"""Flies Multi Lunar Landers with Gymnasium's heuristic pilot or the shipped trained DQN pilot:
in a pygame window (default), or into an animated GIF (--gif out.gif, written with Pillow).

    .venv/bin/python examples/play.py --n_landers 3 --episodes 2
    .venv/bin/python examples/play.py --n_landers 5 --continuous --gif out/landers.gif
    .venv/bin/python examples/play.py --policy trained --n_landers 3 --gif out/trained.gif

The trained pilot (discrete actions) is the Q-network of docs/dqn.md, read with numpy from
examples/dqn/trained.qnet (or --weights PATH); it flies the environment it was trained in:
damage removes only the damaged lander, episodes last up to 2000 steps.

Without --address an embedded mll_server is started (MLL_SERVER_BIN, PATH or build/).
"""

from __future__ import annotations

import argparse
import pathlib
import sys

import multi_lunar_lander as mll

# The trained pilot's reader (numpy only) lives with the trainer in examples/dqn.
sys.path.insert(0, str(pathlib.Path(__file__).resolve().parent / "dqn"))
from mll_dqn.qnet_file import SHIPPED, TrainedPilot  # noqa: E402


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--n_landers", type=int, default=3)
    parser.add_argument("--continuous", action="store_true")
    parser.add_argument("--enable_wind", action="store_true")
    parser.add_argument("--episodes", type=int, default=1)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--policy", choices=("heuristic", "trained"), default="heuristic",
                        help="Gymnasium's heuristic pilot, or the trained DQN network (--weights)")
    parser.add_argument("--weights", default=SHIPPED, help="--policy trained: a .qnet file (default: the shipped one)")
    parser.add_argument("--max_cycles", type=int, default=None,
                        help="steps before truncation (default 500; 2000 with --policy trained)")
    parser.add_argument("--terminate_on_damage", choices=("true", "false"), default=None,
                        help="end every lander's episode when one is damaged (default true; false with "
                        "--policy trained)")
    parser.add_argument("--address", default=None, help="host:port of a running mll_server")
    parser.add_argument("--gif", type=pathlib.Path, help="write an animated GIF here instead of opening a window")
    parser.add_argument("--frame_skip", type=int, default=2, help="GIF: keep every k-th frame (default 2)")
    args = parser.parse_args(argv)
    if args.frame_skip < 1:
        parser.error(f"--frame_skip is {args.frame_skip}; must be >= 1")
    trained = args.policy == "trained"
    if trained and args.continuous:
        parser.error("--policy trained flies discrete actions; drop --continuous")
    if args.max_cycles is None:
        args.max_cycles = 2000 if trained else 500
    if args.terminate_on_damage is None:
        args.terminate_on_damage = "false" if trained else "true"
    pilot = TrainedPilot(args.weights) if trained else None

    env = mll.parallel_env(
        address=args.address,
        render_mode="rgb_array" if args.gif else "human",
        n_landers=args.n_landers,
        continuous=args.continuous,
        enable_wind=args.enable_wind,
        max_cycles=args.max_cycles,
        terminate_on_damage=args.terminate_on_damage == "true",
        # As in training (docs/dqn.md): a damaged lander leaves the scene.
        **({"remove_on_damage": True} if trained else {}),
    )
    frames = []
    try:
        for episode in range(args.episodes):
            observations, _ = env.reset(seed=args.seed + episode)
            step, returns, outcomes = 0, dict.fromkeys(env.possible_agents, 0.0), {}
            while env.agents:
                if args.gif and step % args.frame_skip == 0:
                    frames.append(env.render())
                if trained:
                    chosen = pilot([observations[agent] for agent in env.agents])
                    actions = {agent: int(action) for agent, action in zip(env.agents, chosen)}
                else:
                    actions = {agent: mll.heuristic(observations[agent], args.continuous) for agent in env.agents}
                observations, rewards, _, _, infos = env.step(actions)
                for agent, reward in rewards.items():
                    returns[agent] += reward
                    if "outcome" in infos[agent]:
                        outcomes[agent] = infos[agent]["outcome"]
                step += 1
            if args.gif:
                frames.append(env.render())  # The episode's end: every outcome shown.
            summary = ", ".join(f"{agent} {outcomes.get(agent)} {returns[agent]:.1f}" for agent in env.possible_agents)
            print(f"episode {episode} (seed {args.seed + episode}): {step} steps; {summary}")
    finally:
        env.close()

    if args.gif:
        from PIL import Image

        args.gif.parent.mkdir(parents=True, exist_ok=True)
        images = [Image.fromarray(frame) for frame in frames]
        frame_ms = round(1000 * args.frame_skip / env.metadata["render_fps"])
        images[0].save(args.gif, save_all=True, append_images=images[1:], duration=frame_ms, loop=0, optimize=False)
        print(f"wrote {args.gif} ({len(images)} frames, {frame_ms} ms each)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
